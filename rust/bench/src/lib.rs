//! Holds no code: the crate exists for its criterion benches
//! (`benches/substep.rs`, `benches/radius_graph.rs`), run with
//! `cargo bench -p hybridmpm-bench`.
