//! MLS-MPM solver.
