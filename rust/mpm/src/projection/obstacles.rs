//! Colliders as solid boundaries of the projection step.
//!
//! A cell whose centre lies inside a collider (`sdf < 0`, at the collider's
//! pose for the step) is solid, as a wall cell is: it is never fluid, and
//! the Poisson equation has no flow through its faces (a Neumann
//! condition: a fluid cell's solid neighbour drops out of its row). The
//! faces between a solid cell and a fluid or air cell carry the collider's
//! velocity along their axis (zero at rest: `u_a = v_obs,a`), before the
//! solve (the divergence reads them) and after it (g2p reads them). A face
//! with solid cells on both sides lies inside the collider; after the solve
//! it takes the collider's velocity where its axis is the normal's (the
//! outward normal's largest component at the face), and the fluid's
//! velocity from the first face out along the normal where its axis is
//! tangential: free slip, so a particle beside the collider reads its
//! neighbours' tangential velocity, not a wall's zero (the walls carry the
//! fluid's tangential velocity into theirs the same way). After g2p, and after each frame that moves
//! the particles on at the step's velocity, a particle deeper than
//! [`PROJECT_DEPTH_CELLS`] inside a collider goes back onto its surface
//! ([`Collider::project_particle`]), as in the explicit engine.
//!
//! The obstacles are free slip: a collider that is sticky or has friction
//! is refused by the solver (`solver/large_step.rs`). The staircase of
//! solid cells resolves a collider to a cell; a collider thinner than the
//! two cells [`crate::collider::MIN_BOX_THICKNESS_CELLS`] asks for may hold
//! no cell centre and let the water through (the explicit engine refuses
//! it on that grid already).

use nalgebra::SVector;

use super::bodies::StepBody;
use super::{Projection, shape, strides};
use crate::collider::{Collider, PROJECT_DEPTH_CELLS, Reach, ShallowCells};
use crate::particles::Particle;

/// The colliders a projection step sees: each at its pose for the step,
/// its velocity in the frame [m/s] (`None`: at rest) and its shallow cells
/// (a sampled shape's, for the particle projection's reach), index for index.
#[derive(Clone, Copy)]
pub struct StepColliders<'a, const D: usize> {
    pub colliders: &'a [Collider<D>],
    pub velocity: &'a [Option<SVector<f32, D>>],
    pub shallow: &'a [Option<ShallowCells>],
    /// The rigid bodies, solid cells after the colliders' (`bodies.rs`).
    pub bodies: &'a [StepBody<D>],
}

impl<const D: usize> StepColliders<'_, D> {
    /// No colliders.
    pub fn none() -> StepColliders<'static, D> {
        StepColliders {
            colliders: &[],
            velocity: &[],
            shallow: &[],
            bodies: &[],
        }
    }

    /// The velocity of collider `k` [m/s] (zero at rest).
    fn velocity_of(&self, k: usize) -> SVector<f32, D> {
        self.velocity
            .get(k)
            .copied()
            .flatten()
            .unwrap_or_else(SVector::zeros)
    }

    /// The colliders that project particles, each with where it can act ([`Collider::reach`], made once a
    /// step, not once a particle) and its velocity: what [`project`] reads.
    pub(super) fn projecting(&self, dx: f32) -> Vec<Projecting<'_, D>> {
        let depth = PROJECT_DEPTH_CELLS * dx;
        self.colliders
            .iter()
            .enumerate()
            .filter(|(_, col)| col.project)
            .map(|(k, col)| {
                let shallow = self.shallow.get(k).and_then(Option::as_ref);
                (
                    col,
                    col.reach(depth, shallow),
                    self.velocity.get(k).and_then(Option::as_ref),
                )
            })
            .collect()
    }
}

/// A projecting collider, where it can act and its velocity (None: at rest).
pub(super) type Projecting<'a, const D: usize> =
    (&'a Collider<D>, Reach<'a, D>, Option<&'a SVector<f32, D>>);

/// Puts a particle deeper than [`PROJECT_DEPTH_CELLS`] inside a collider of `projecting` back onto its surface,
/// then within `(lo, hi)`.
#[inline]
pub(super) fn project<const D: usize>(
    projecting: &[Projecting<'_, D>],
    p: &mut Particle<D>,
    (lo, hi): (f32, f32),
) {
    let mut moved = false;
    for (col, reach, u) in projecting {
        moved |= col.project_particle(reach, &mut p.x, &mut p.v, *u, None);
    }
    if moved {
        for d in 0..D {
            p.x[d] = p.x[d].clamp(lo, hi);
        }
    }
}

/// The particles of `chunk` move on at their velocity for `dt` [s], kept inside `bounds` and out of
/// the colliders `projecting` ([`super::Projection::drift`]); returns the fastest one's speed [m/s].
pub(super) fn drift_chunk<const D: usize>(
    chunk: &mut [Particle<D>],
    dt: f32,
    (lo, hi): (f32, f32),
    projecting: &[Projecting<'_, D>],
) -> f32 {
    let mut vmax = 0.0f32;
    for p in chunk.iter_mut() {
        super::transfer::move_on(p, dt, (lo, hi));
        if !projecting.is_empty() {
            project(projecting, p, (lo, hi));
        }
        vmax = vmax.max(crate::dim::norm(&p.v));
    }
    vmax
}

impl<const D: usize> Projection<D> {
    /// Marks the solid cells of `cols` (a cell is solid where its centre lies inside a collider or a
    /// body; the first that holds it names it, colliders first) inside the walls, and keeps each
    /// collider's velocity.
    pub(super) fn mark_solid(&mut self, cols: &StepColliders<'_, D>) {
        for &c in &self.solid_cells {
            self.solid[c] = 0;
        }
        self.solid_cells.clear();
        self.obstacle_velocity.clear();
        for (k, col) in cols.colliders.iter().enumerate() {
            self.obstacle_velocity.push(cols.velocity_of(k));
            let (centre, r) = (col.shape.center(), col.shape.bounding_radius());
            self.mark_inside(k, centre, r, |x| col.shape.sdf(x));
        }
        let first = cols.colliders.len();
        for (b, body) in cols.bodies.iter().enumerate() {
            let pose = &body.pose;
            let r = pose.shape.bounding_radius();
            self.mark_inside(first + b, pose.center, r, |x| pose.sdf_normal(x).0);
        }
    }

    /// Marks the cells not yet solid whose centres lie within `r` of `centre` and where `sdf` is
    /// negative as solid `k`'s (collider `k`, or body `k − colliders`), inside the walls.
    fn mark_inside(
        &mut self,
        k: usize,
        centre: SVector<f32, D>,
        r: f32,
        sdf: impl Fn(&SVector<f32, D>) -> f32,
    ) {
        let (n, ws, dx) = (self.n, self.ws, self.dx);
        let stride = strides(&shape::<D>(n, None));
        // the cells whose centres the bounding sphere may hold, inside the walls
        let lo: [usize; D] = std::array::from_fn(|d| {
            let i = ((centre[d] - r) / dx - 0.5).floor().max(ws as f32);
            (i as usize).min(n - ws)
        });
        let hi: [usize; D] = std::array::from_fn(|d| {
            let i = ((centre[d] + r) / dx - 0.5).ceil().max(0.0);
            (i as usize).min(n - ws - 1)
        });
        if (0..D).any(|d| lo[d] > hi[d]) {
            return;
        }
        let count: [usize; D] = std::array::from_fn(|d| hi[d] - lo[d] + 1);
        super::transfer::for_each_node(&count, |_, off| {
            let idx: [usize; D] = std::array::from_fn(|d| lo[d] + off[d]);
            let c: usize = (0..D).map(|d| idx[d] * stride[d]).sum();
            if self.solid[c] != 0 {
                return;
            }
            let x = SVector::<f32, D>::from_fn(|d, _| (idx[d] as f32 + 0.5) * dx);
            if sdf(&x) < 0.0 {
                self.solid[c] = (k + 1) as u16;
                self.solid_cells.push(c);
            }
        });
    }

    /// Whether cell `c` (index `idx`) is a collider's solid cell.
    #[inline(always)]
    pub(super) fn in_obstacle(&self, c: usize) -> bool {
        self.solid[c] != 0
    }

    /// The faces of the solid cells (module docs): a face to a fluid or air cell takes the collider's
    /// velocity along its axis (a body's: its point velocity at the face's centre, `bodies.rs`). With `inside`, after the solve, so do the faces inside the collider
    /// whose axis is the normal's (the largest component of the outward normal at the face), and one
    /// whose axis is tangential takes the velocity of the first face out along the normal that is not
    /// inside (up to [`MAX_EXTRAPOLATION_CELLS`] cells; the collider's where there is none): free slip,
    /// the fluid's tangential velocity carried into the collider as the walls carry it into theirs. A
    /// face to a wall cell keeps what the walls set.
    pub(super) fn obstacle_faces(&mut self, cols: &StepColliders<'_, D>, inside: bool) {
        if self.solid_cells.is_empty() {
            return;
        }
        let (n, dx) = (self.n, self.dx);
        let g = self.grid();
        let stride_c = strides(&shape::<D>(n, None));
        let first = cols.colliders.len();
        for i in 0..self.solid_cells.len() {
            let s = self.solid_cells[i];
            let k = self.solid[s] as usize - 1;
            let idx = self.unflat(s);
            for a in 0..D {
                let st = strides(&shape::<D>(n, Some(a)));
                let low_face: usize = (0..D).map(|d| idx[d] * st[d]).sum();
                for (face, other_idx, other) in [
                    (low_face, idx[a] - 1, s - stride_c[a]),
                    (low_face + st[a], idx[a] + 1, s + stride_c[a]),
                ] {
                    let mut j = idx;
                    j[a] = other_idx;
                    if g.in_walls(&j) {
                        continue; // the walls' condition holds there
                    }
                    let to_fluid = !self.in_obstacle(other);
                    if !(to_fluid || inside && face == low_face) {
                        continue; // inside: visited once, as the upper cell's low face
                    }
                    // the face's centre
                    let x = SVector::<f32, D>::from_fn(|d, _| {
                        let shift = if d != a {
                            0.5
                        } else if face == low_face {
                            0.0
                        } else {
                            1.0
                        };
                        (idx[d] as f32 + shift) * dx
                    });
                    let v_solid = match k.checked_sub(first) {
                        None => self.obstacle_velocity[k][a],
                        Some(b) => self.body_point_velocity(cols.bodies, b, &x)[a],
                    };
                    if to_fluid {
                        self.vel[a][face] = v_solid;
                        continue;
                    }
                    let nrm = match k.checked_sub(first) {
                        None => cols.colliders[k].shape.normal(&x),
                        Some(b) => cols.bodies[b].pose.sdf_normal(&x).1,
                    };
                    let b = nrm.iamax();
                    self.vel[a][face] = if b == a {
                        v_solid
                    } else {
                        self.outside_face(a, idx, b, nrm[b] > 0.0)
                            .unwrap_or(v_solid)
                    };
                }
            }
        }
    }

    /// The velocity of the first face of component `a` out from the low face of cell `idx` along axis
    /// `b` (up if `up`) that is not inside a collider, within [`MAX_EXTRAPOLATION_CELLS`] cells.
    fn outside_face(&self, a: usize, idx: [usize; D], b: usize, up: bool) -> Option<f32> {
        let (n, g) = (self.n, self.grid());
        let stride_c = strides(&shape::<D>(n, None));
        let st = strides(&shape::<D>(n, Some(a)));
        let mut j = idx;
        for _ in 0..MAX_EXTRAPOLATION_CELLS {
            j[b] = if up { j[b] + 1 } else { j[b].checked_sub(1)? };
            let mut below = j;
            below[a] = below[a].checked_sub(1)?;
            if g.in_walls(&j) || g.in_walls(&below) {
                return None;
            }
            let c: usize = (0..D).map(|d| j[d] * stride_c[d]).sum();
            if !(self.in_obstacle(c) && self.in_obstacle(c - stride_c[a])) {
                let face: usize = (0..D).map(|d| j[d] * st[d]).sum();
                return Some(self.vel[a][face]);
            }
        }
        None
    }
}

/// The most cells a tangential velocity is carried into a collider from the fluid beside it (the
/// quadratic stencil reaches a cell and a half).
pub const MAX_EXTRAPOLATION_CELLS: usize = 3;
