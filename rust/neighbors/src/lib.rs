//! Radius graph.
