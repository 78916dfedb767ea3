//! Rigid bodies that the fluid moves and that push back (two-way coupling).
//!
//! A body is a collider whose velocity comes from its state and whose
//! grid-node momentum changes are summed into an impulse:
//!
//! - `mod.rs`: a body's shape and initial state ([`Body`]) and its checks
//!   against the grid;
//! - `hull.rs`: a convex body in 3D ([`Hull`]): the hull of a mesh's points,
//!   its face planes and mass properties;
//! - `pose.rs`: a body where it is during a substep ([`BodyPose`]): its
//!   signed distance, outward normal and point velocity `v + ω × r`, what the
//!   grid update's collider pass reads, and the exact sums of the impulses
//!   it writes ([`ImpulseSum`]);
//! - `world.rs`: the bodies' dynamics and contacts behind one small trait
//!   ([`world::RigidWorld`]) and the plain specs it speaks; `rapier2.rs` /
//!   `rapier3.rs` implement it with rapier (the only files that name its
//!   types), and `rapier.rs` picks one by dimension;
//! - `system.rs`: the solver's bodies between substeps ([`Bodies`]): their
//!   exact state (what a checkpoint carries), the poses of the substep under
//!   way, the impulses summed, the rapier step.
//!
//! Coupling, each substep (docs/bodies.md): a grid node with mass whose
//! position lies inside a body or less than [`BODY_REACH_CELLS`] cells
//! outside its surface takes the body's point velocity for its normal
//! component when it approaches the body (the `Separate` condition relative
//! to `v + ω × r`, with Coulomb friction on the tangential part); the node's
//! momentum change `m (v' − v)`, with its sign flipped, is an impulse on the
//! body at the node. The impulses are summed in fixed point (integer sums:
//! the same bits in any order, for any thread count) and applied to rapier
//! before it steps with the substep's `dt`.

mod hull;
pub(crate) mod pose;
mod rapier;
mod rapier2;
mod rapier3;
mod system;
pub(crate) mod world;

pub use hull::{Hull, MAX_HULL_POINTS, mass_properties};
pub use pose::{BodyPose, Coupled, ImpulseSum, SUM_LANES};
pub use system::{Bodies, BodyState};

use std::sync::Arc;

use nalgebra::{SMatrix, SVector};

use crate::error::{MpmError, Result};

/// How far outside a body's surface grid nodes are coupled to it, in cells.
/// Coupling only the nodes inside a body lets water sit up to a cell inside
/// its outline and leaves buoyancy 5–15 % short; nodes to about a cell
/// outside close the gap (docs/bodies.md has the measurement).
pub const BODY_REACH_CELLS: f32 = 1.0;

/// Most bodies a solver takes.
pub const MAX_BODIES: usize = 64;

/// The thinnest body (its smallest half extent or radius), in cells: as
/// thin an obstacle is refused, since the fluid leaks through it.
pub const MIN_BODY_HALF_CELLS: f32 = 1.0;

/// The lightest body [kg/m³], about air's density. Below about 1e-4 kg/m³
/// a body's mass and inertia are so small against the water it couples
/// with that the coupled solve's round-off (a torque on a sphere, whose
/// normals should all pass through its centre) spins and throws it: a
/// 1e-6 kg/m³ ball at the surface flew at 24–133 m/s; at 1e-3 kg/m³ and
/// above balls and boxes rise at the flow's pace (docs/bodies.md).
pub const MIN_BODY_DENSITY: f32 = 1.0;

/// The heaviest body [kg/m³], about four times osmium's. rapier integrates
/// in `f32`: a body of more than about 1e20 kg does not fall at all (its
/// velocity increment `g Δt` is lost), and in the unit domain a body under
/// this density weighs at most 1e5 kg.
pub const MAX_BODY_DENSITY: f32 = 1.0e5;

/// The fastest a body's point may move [m/s] (`|v|` per axis and the rim
/// speed `|ω| R`), as a block's velocity per axis (the scene files' bound);
/// the simulator also refuses a body whose speed needs more than
/// `max_substeps` substeps a frame.
pub const MAX_BODY_SPEED: f32 = 1000.0;

/// How far a restored body may lie past the walls' inner faces, in cells:
/// rapier lets a resting body sink into a wall by a small fraction of a
/// cell, so a checkpoint of a body on the floor is not exactly inside.
pub const BODY_STATE_WALL_SLACK_CELLS: f32 = 1.0;

/// A body's shape, centred on its centre of mass, in its own frame.
#[derive(Clone, Debug, PartialEq)]
pub enum BodyShape<const D: usize> {
    /// A box of these half extents [m] along the body's axes.
    Box { half_extents: SVector<f32, D> },
    /// A sphere (a circle in 2D) of this radius [m].
    Ball { radius: f32 },
    /// A capsule: the points within `radius` [m] of the segment from
    /// `-half_height` to `half_height` [m] along the body's y axis.
    Capsule { radius: f32, half_height: f32 },
    /// A convex polyhedron (3D only).
    Hull(Arc<Hull>),
}

impl<const D: usize> BodyShape<D> {
    /// Volume [m³] (area [m²] in 2D).
    pub fn volume(&self) -> f32 {
        use std::f32::consts::PI;
        match self {
            BodyShape::Box { half_extents } => half_extents.iter().map(|h| 2.0 * h).product(),
            BodyShape::Ball { radius } => {
                if D == 2 {
                    PI * radius * radius
                } else {
                    4.0 / 3.0 * PI * radius.powi(3)
                }
            }
            BodyShape::Capsule {
                radius: r,
                half_height: h,
            } => {
                if D == 2 {
                    4.0 * r * h + PI * r * r
                } else {
                    PI * r * r * 2.0 * h + 4.0 / 3.0 * PI * r.powi(3)
                }
            }
            BodyShape::Hull(hull) => hull.volume,
        }
    }

    /// The inertia tensor about the centre of mass in the body's axes of a
    /// body of mass `m` [kg] (2D: about z, entry (2, 2)) [kg·m²]: exact for
    /// each shape (a capsule's: its cylinder, or rectangle, and its two
    /// half balls, or half discs, moved to their centroids).
    pub fn local_inertia(&self, m: f64) -> [[f64; 3]; 3] {
        let diag = |d: [f64; 3]| {
            std::array::from_fn(|i| std::array::from_fn(|j| if i == j { d[i] } else { 0.0 }))
        };
        match self {
            BodyShape::Box { half_extents: h } => {
                let h2: [f64; 3] =
                    std::array::from_fn(|d| if d < D { (h[d] as f64).powi(2) } else { 0.0 });
                diag([
                    m / 3.0 * (h2[1] + h2[2]),
                    m / 3.0 * (h2[0] + h2[2]),
                    m / 3.0 * (h2[0] + h2[1]),
                ])
            }
            BodyShape::Ball { radius } => {
                let r2 = (*radius as f64).powi(2);
                let k = if D == 2 { 0.5 } else { 0.4 };
                diag([k * m * r2; 3])
            }
            BodyShape::Capsule {
                radius,
                half_height,
            } => {
                let (r, h) = (*radius as f64, *half_height as f64);
                let pi = std::f64::consts::PI;
                if D == 2 {
                    // rectangle 2r × 2h and a disc split at y = ±h
                    let (a_rect, a_disc) = (4.0 * r * h, pi * r * r);
                    let (m_rect, m_disc) = (
                        m * a_rect / (a_rect + a_disc),
                        m * a_disc / (a_rect + a_disc),
                    );
                    let iz = m_rect * (r * r + h * h) / 3.0
                        + m_disc * (0.5 * r * r + h * h + 8.0 * h * r / (3.0 * pi));
                    diag([0.0, 0.0, iz])
                } else {
                    let (v_cyl, v_ball) = (pi * r * r * 2.0 * h, 4.0 / 3.0 * pi * r.powi(3));
                    let (m_cyl, m_ball) =
                        (m * v_cyl / (v_cyl + v_ball), m * v_ball / (v_cyl + v_ball));
                    let iy = 0.5 * m_cyl * r * r + 0.4 * m_ball * r * r;
                    let ix = m_cyl * (0.25 * r * r + h * h / 3.0)
                        + m_ball * (0.4 * r * r + h * h + 0.75 * h * r);
                    diag([ix, iy, ix])
                }
            }
            BodyShape::Hull(hull) => {
                let rho = m / hull.volume as f64;
                hull.unit_inertia.map(|row| row.map(|x| rho * x))
            }
        }
    }

    /// Radius of the smallest ball about the centre that holds the shape [m].
    pub fn bounding_radius(&self) -> f32 {
        match self {
            BodyShape::Box { half_extents } => half_extents.norm(),
            BodyShape::Ball { radius } => *radius,
            BodyShape::Capsule {
                radius,
                half_height,
            } => radius + half_height,
            BodyShape::Hull(hull) => hull.radius,
        }
    }

    /// Half of the shape's thinnest extent [m].
    fn thinnest_half(&self) -> f32 {
        match self {
            BodyShape::Box { half_extents } => half_extents.min(),
            BodyShape::Ball { radius } | BodyShape::Capsule { radius, .. } => *radius,
            BodyShape::Hull(hull) => hull.thinnest_half,
        }
    }

    /// The lowest and highest coordinate of the shape along world axis `d`,
    /// relative to its centre of mass, when rotated by `rotation` [m].
    pub fn span(&self, rotation: &SMatrix<f32, D, D>, d: usize) -> (f32, f32) {
        let reach = match self {
            BodyShape::Box { half_extents } => (0..D)
                .map(|k| (rotation[(d, k)] * half_extents[k]).abs())
                .sum(),
            BodyShape::Ball { radius } => *radius,
            BodyShape::Capsule {
                radius,
                half_height,
            } => (rotation[(d, 1)] * half_height).abs() + radius,
            BodyShape::Hull(hull) => return hull.span(|i, j| rotation[(i, j)], d),
        };
        (-reach, reach)
    }
}

/// A rigid body: shape, initial pose and velocity, density, and Coulomb
/// friction against the fluid ([`crate::params::BodyParams::build`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Body<const D: usize> {
    pub shape: BodyShape<D>,
    /// Centre of mass [m].
    pub center: SVector<f32, D>,
    /// Rotation (columns: the body's axes in world coordinates).
    pub rotation: SMatrix<f32, D, D>,
    /// Density [kg/m³].
    pub density: f32,
    /// Velocity of the centre of mass [m/s].
    pub velocity: SVector<f32, D>,
    /// Angular velocity [rad/s] (2D: about z, the last component).
    pub angular_velocity: [f32; 3],
    /// Coulomb friction coefficient against the fluid.
    pub friction: f32,
}

impl<const D: usize> Body<D> {
    /// Mass [kg; per unit depth in 2D].
    pub fn mass(&self) -> f32 {
        self.density * self.shape.volume()
    }

    /// The body in rapier's terms: a box or a ball by density (rapier's mass
    /// properties equal ours), a capsule or a hull with ours
    /// ([`BodyShape::local_inertia`]) given to rapier.
    pub(crate) fn spec(&self) -> world::BodySpec {
        let pad = |v: &SVector<f32, D>| std::array::from_fn(|d| if d < D { v[d] } else { 0.0 });
        let shape = match &self.shape {
            BodyShape::Box { half_extents } => world::ShapeSpec::Box(pad(half_extents)),
            BodyShape::Ball { radius } => world::ShapeSpec::Ball(*radius),
            BodyShape::Capsule {
                radius,
                half_height,
            } => world::ShapeSpec::Capsule(*radius, *half_height),
            BodyShape::Hull(hull) => world::ShapeSpec::Hull(hull.clone()),
        };
        let mass = match self.shape {
            BodyShape::Box { .. } | BodyShape::Ball { .. } => None,
            _ => Some((self.mass(), self.shape.local_inertia(self.mass() as f64))),
        };
        world::BodySpec {
            shape,
            density: self.density,
            mass,
        }
    }

    /// Whether this body at state `state` overlaps `other` at `other_state`
    /// (parry's intersection test on rapier's shapes).
    pub fn overlaps(&self, state: &BodyState, other: &Body<D>, other_state: &BodyState) -> bool {
        rapier::overlap(
            D,
            (&self.spec().shape, state),
            (&other.spec().shape, other_state),
        )
    }

    /// Checks the body against a grid of spacing `dx` whose walls are
    /// `wall_cells` thick: thick enough for the grid (at least
    /// [`MIN_BODY_HALF_CELLS`] cells a half extent or radius, field
    /// `half_extents` / `radius`), inside the walls (field `center`),
    /// finite speeds (`velocity`, `angular_velocity`). `field` prefixes the
    /// names (e.g. `bodies[2]`).
    pub fn validate(&self, field: &str, dx: f32, wall_cells: usize) -> Result<()> {
        let size_field = match self.shape {
            BodyShape::Box { .. } => "half_extents",
            BodyShape::Ball { .. } | BodyShape::Capsule { .. } => "radius",
            BodyShape::Hull(ref hull) => hull.key,
        };
        let thin = self.shape.thinnest_half();
        if !(thin >= MIN_BODY_HALF_CELLS * dx) {
            return Err(MpmError::invalid(
                format!("{field}.{size_field}"),
                format!(
                    "too thin for the grid: its smallest half extent {thin} m is under {MIN_BODY_HALF_CELLS} cell ({} m); the fluid would leak through",
                    MIN_BODY_HALF_CELLS * dx
                ),
            ));
        }
        if let BodyShape::Capsule { half_height, .. } = self.shape
            && !(half_height >= MIN_BODY_HALF_CELLS * dx)
        {
            return Err(MpmError::invalid(
                format!("{field}.half_height"),
                format!(
                    "must be at least {MIN_BODY_HALF_CELLS} cell ({} m), got {half_height} m (a shorter capsule is a ball: give shape 'sphere')",
                    MIN_BODY_HALF_CELLS * dx
                ),
            ));
        }
        self.check_pose(field, &self.center, &self.rotation, dx, wall_cells, 0.0)?;
        self.check_density(field)?;
        let speeds = |v: &[f32]| v.iter().all(|x| x.is_finite() && x.abs() <= MAX_BODY_SPEED);
        if !speeds(self.velocity.as_slice()) {
            return Err(MpmError::invalid(
                format!("{field}.velocity"),
                format!(
                    "each component must be finite and at most {MAX_BODY_SPEED} m/s in size, got {:?}",
                    self.velocity.as_slice()
                ),
            ));
        }
        let rim = rim_speed(&self.angular_velocity, self.shape.bounding_radius());
        if !(rim <= MAX_BODY_SPEED) {
            return Err(MpmError::invalid(
                format!("{field}.angular_velocity"),
                format!(
                    "its rim moves at |ω|·R = {rim} m/s (ω = {:?} rad/s, R = {} m); at most {MAX_BODY_SPEED} m/s",
                    if D == 2 {
                        &self.angular_velocity[2..]
                    } else {
                        &self.angular_velocity[..]
                    },
                    self.shape.bounding_radius()
                ),
            ));
        }
        Ok(())
    }

    /// The density within [[`MIN_BODY_DENSITY`], [`MAX_BODY_DENSITY`]]
    /// kg/m³, and the mass and inertia `f32` normal numbers, as the core
    /// and rapier store them (field `density`).
    pub fn check_density(&self, field: &str) -> Result<()> {
        let rho = self.density;
        if !(rho.is_finite() && (MIN_BODY_DENSITY..=MAX_BODY_DENSITY).contains(&rho)) {
            return Err(MpmError::invalid(
                format!("{field}.density"),
                format!(
                    "must be in [{MIN_BODY_DENSITY}, {MAX_BODY_DENSITY:e}] kg/m^3, got {rho:?}"
                ),
            ));
        }
        let m = self.mass();
        let inertia = self.shape.local_inertia(m as f64);
        let normal = |x: f64| (x as f32).is_normal() && x > 0.0;
        let inertia_ok = (0..3)
            .filter(|&k| D == 3 || k == 2)
            .all(|k| normal(inertia[k][k]));
        if !(m.is_normal() && m > 0.0 && inertia_ok) {
            return Err(MpmError::invalid(
                format!("{field}.density"),
                format!(
                    "gives a mass of {m} kg and an inertia that are not normal float32 numbers"
                ),
            ));
        }
        Ok(())
    }

    /// The body at centre `center` and rotation `rotation` inside the walls
    /// (the inner faces of `wall_cells`-thick bands on a grid of spacing
    /// `dx`), give or take `slack` [m]; field `center`.
    pub fn check_pose(
        &self,
        field: &str,
        center: &SVector<f32, D>,
        rotation: &SMatrix<f32, D, D>,
        dx: f32,
        wall_cells: usize,
        slack: f32,
    ) -> Result<()> {
        let lo = wall_cells as f32 * dx - slack;
        let hi = 1.0 - wall_cells as f32 * dx + slack;
        // the body's extent along each axis
        for d in 0..D {
            let (a, b) = self.shape.span(rotation, d);
            let c = center[d];
            if !(c + a >= lo && c + b <= hi) {
                return Err(MpmError::invalid(
                    format!("{field}.center"),
                    format!(
                        "the body must lie inside the walls, [{lo}, {hi}] m along axis {d}: it spans [{}, {}]",
                        c + a,
                        c + b
                    ),
                ));
            }
        }
        Ok(())
    }

    /// A checkpoint's state for this body: finite, a unit rotation
    /// (quaternion norm within 1e-3 of 1), the body inside the walls within
    /// [`BODY_STATE_WALL_SLACK_CELLS`], its points no faster than
    /// [`MAX_BODY_SPEED`]. Errors name `field` (e.g. `body_state[1]`).
    pub fn check_state(
        &self,
        field: &str,
        state: &BodyState,
        dx: f32,
        wall_cells: usize,
    ) -> Result<()> {
        let all = state
            .x
            .iter()
            .chain(&state.q)
            .chain(&state.v)
            .chain(&state.w);
        if !all.clone().all(|x| x.is_finite()) {
            return Err(MpmError::invalid(field, "must be finite"));
        }
        let q = &state.q;
        let qn = if D == 2 {
            (q[0] * q[0] + q[1] * q[1]).sqrt()
        } else {
            q.iter().map(|x| x * x).sum::<f32>().sqrt()
        };
        if !((qn - 1.0).abs() <= 1e-3) {
            return Err(MpmError::invalid(
                field,
                format!("the rotation is not a unit quaternion (norm {qn})"),
            ));
        }
        let center = SVector::<f32, D>::from_fn(|d, _| state.x[d]);
        self.check_pose(
            field,
            &center,
            &state.rotation(),
            dx,
            wall_cells,
            BODY_STATE_WALL_SLACK_CELLS * dx,
        )?;
        let v = (0..D).map(|d| state.v[d] * state.v[d]).sum::<f32>().sqrt();
        let speed = v + rim_speed(&state.w, self.shape.bounding_radius());
        if !(speed <= MAX_BODY_SPEED * (D as f32).sqrt() + MAX_BODY_SPEED) {
            return Err(MpmError::invalid(
                field,
                format!(
                    "the body's fastest point moves at {speed} m/s, past what a frame can simulate"
                ),
            ));
        }
        Ok(())
    }
}

/// `|ω| R` [m/s].
fn rim_speed(w: &[f32; 3], r: f32) -> f32 {
    (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt() * r
}
