//! MLS-MPM solver for water, Drucker–Prager sand, elastic solids, snow and
//! viscoplastic mud, and their mixture, with
//! static signed-distance obstacles, in 2D and 3D from one source.
//!
//! Method: Hu et al. 2018 (MLS-MPM, APIC transfers, quadratic B-splines);
//! sand: Klár et al. 2016 (Hencky strain, SVD return mapping) with the volume
//! correction of Tampubolon et al. 2017; elastic: fixed-corotated
//! (Stomakhin et al. 2012) or neo-Hookean; snow: Stomakhin et al. 2013;
//! viscoplastic: von Mises on the Hencky strain with viscous relaxation. Sparse block grid: only blocks near
//! particles are touched. Deterministic for any thread count.
//!
//! Layout: `kernel` (quadratic B-spline weights, shared with `grid_mass`,
//! `transfer` and `surface`), `material` (a file per constitutive model:
//! water, sand, elastic, snow, viscoplastic, behind one trait, each with
//! its parameters and their schema), `boundary`,
//! `collider/` (a file per concept: shape, sampled signed distance, motion,
//! validation, particle projection and its reach, boundary condition) and
//! `params/` (the solver-wide parameters, walls, obstacles and bodies, and
//! the materials' parameters re-exported; `params` uses `material` and
//! `collider`, both use `boundary`), `solver` (one file per substep stage:
//! grid, p2g, grid_update, g2p, and the CFL frame loop), `checkpoint`;
//! outside the solver, on the same kernel: `grid_mass` (the accuracy
//! metric's field), `transfer` (the grid model's transfers), `surface` (the
//! fluid surfaces' p2g); `projection` (incompressible APIC water on a MAC
//! grid with a pressure projection: the large step, docs/large-step.md).

// Numeric kernels index several small arrays with one loop variable (`for d
// in 0..D`), and `!(x > 0.0)` deliberately also rejects NaN.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord)]

pub mod body;
pub mod boundary;
pub mod checkpoint;
pub mod collider;
pub mod dim;
pub mod error;
pub mod grid_mass;
pub mod isa;
mod kernel;
mod material;
pub mod params;
pub mod particles;
pub mod pool;
pub mod projection;
pub mod solver;
pub mod surface;
pub mod transfer;
mod v4;

pub use body::{Body, BodyShape, BodyState};
pub use boundary::BoundaryCondition;
pub use collider::{Collider, Shape};
pub use dim::{Dim, DimOps};
pub use error::{MpmError, Result, human_bytes};
pub use grid_mass::{grid_mass, grid_mass_bytes, grid_mass_with_budget};
pub use isa::Isa;
pub use material::param_structs::*;
pub use material::schema::{Limit, MaterialSchema, Param, ParamValue};
pub use material::{ElasticModel, MaterialParams, material_schema};
pub use params::{
    BodyParams, BodyShapeKind, ColliderParams, Integrator, ShapeKind, SolverParams, WallFace,
    WallParams,
};
pub use particles::{Material, Particle, lattice, lattice_box};
pub use pool::shared_pool;
pub use solver::{FrameStats, Solver};
pub use surface::surface_p2g;
pub use transfer::{Pressure, TransferGrid, advect, g2p, p2g};
