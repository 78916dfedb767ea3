//! The engine's integration tests, one test binary (`cargo test -p
//! hybridmpm-mpm --test engine`; a module's tests by its name, e.g.
//! `--test engine golden::`). One binary compiles the solver's 2D and 3D
//! copies once for all of them: thirteen binaries compiled them thirteen
//! times (about 1,150 s of the 1,715 s of CPU that building the Rust
//! tests took on a 2-core machine).

mod bodies;
mod body_contacts;
mod body_shapes;
mod body_stability;
mod common;
mod golden;
mod large_step;
mod large_step_obstacles;
mod limits;
mod material_checks;
mod materials;
mod moving_collider;
mod physics;
mod projection;
mod sampled_collider;
mod state_fuzz;
