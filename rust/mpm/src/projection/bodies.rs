//! Rigid bodies in the projection step, coupled both ways in its one
//! pressure solve (after Batty, Bertails & Bridson 2007, "A fast
//! variational framework for accurate solid-fluid coupling", on the
//! staircase of solid cells).
//!
//! A cell whose centre lies inside a body (at its pose at the step's start)
//! is that body's solid cell, as a collider's is (`obstacles.rs`): its
//! faces carry the body's point velocity `v + ω × r` instead of one
//! velocity. The body's generalized velocity `V = [v, ω]` moves the face
//! `f` between a fluid cell and one of its cells at `J_f·V`, with
//! `J_f = s·[e_a, r_f × e_a]` (`e_a` the face's axis, `s` = +1 where the
//! fluid cell lies below the face, −1 above it, `r_f` the face's centre
//! from the centre of mass). The fluid cell's pressure pushes the body
//! through that face with the force `p·dx^(D−1)·s·e_a`, so a step's
//! pressure impulse on the body is `dt·dx^(D−1)·Σ_f J_fᵀ p_f` and its
//! velocity after the step
//!
//! `V' = V* + M⁻¹·dt·dx^(D−1)·Σ_f J_fᵀ p_f`,
//!
//! `V*` its velocity with the step's gravity. Asking the divergence of each
//! fluid cell to vanish with the faces at `J_f·V'` adds
//! `ρ·dx^D·J M⁻¹ Jᵀ` (the water a cell holds, against the body's mass
//! matrix) to the Poisson matrix: symmetric and positive semi-definite, so
//! the step stays one CG solve. A heavy body barely gives way (a collider
//! at rest in the limit); a light one moves with the water: the coupling
//! is implicit, so a body lighter than the water it moves (its added mass)
//! steps as stably as a heavy one. The solve gives each body its impulse
//! and its velocity change ([`Projection::body_steps`]); the solver applies
//! them to the bodies' rigid world and steps it (contacts, gravity:
//! `solver/large_step.rs`), then puts the particles that ended inside a
//! body back onto its surface ([`push_out_of_bodies`]).

use nalgebra::SVector;
use rayon::prelude::*;

use super::{Projection, shape, strides};
use crate::body::BodyPose;
use crate::body::pose::point_velocity;
use crate::particles::Particle;

/// A body as one projection step sees it.
#[derive(Clone, Debug)]
pub struct StepBody<const D: usize> {
    /// Its pose at the step's start, with the velocity the step starts
    /// from: the last one plus the step's gravity (`V*`).
    pub pose: BodyPose<D>,
    /// `1/m` [1/kg] (2D: per metre of depth).
    pub inv_mass: f64,
    /// The inverse inertia tensor in world axes [1/(kg·m²)] (2D: only the
    /// entry (2, 2), about z).
    pub inv_inertia: [[f64; 3]; 3],
}

impl<const D: usize> StepBody<D> {
    /// `M⁻¹·g` for a generalized force `g` (lanes: force, torque).
    fn apply_inverse(&self, g: &[f64; 6]) -> [f64; 6] {
        let mut out = [0.0; 6];
        for k in 0..D {
            out[k] = self.inv_mass * g[k];
        }
        for k in 0..3 {
            out[3 + k] = (0..3).map(|l| self.inv_inertia[k][l] * g[3 + l]).sum();
        }
        out
    }
}

/// A face between a fluid cell (its row in the solve) and a body's solid
/// cell, with its `J_f`.
#[derive(Clone, Copy, Debug)]
pub(super) struct BodyFace {
    pub row: u32,
    pub body: u16,
    pub j: [f64; 6],
}

/// What a step did to a body: its pressure impulse (N·s and N·m·s, lanes
/// as [`crate::body::ImpulseSum`]'s; 2D per metre of depth) and its
/// velocity change `M⁻¹·impulse` [m/s, rad/s].
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct BodyStep {
    pub impulse: [f64; 6],
    pub delta: [f64; 6],
}

#[inline]
fn dot6(a: &[f64; 6], b: &[f64; 6]) -> f64 {
    (0..6).map(|k| a[k] * b[k]).sum()
}

impl<const D: usize> Projection<D> {
    /// Each body's velocity in the step starts at its `V*` (before the faces read it).
    pub(super) fn start_bodies(&mut self, bodies: &[StepBody<D>]) {
        self.body_velocity.clear();
        self.body_velocity.extend(bodies.iter().map(|b| {
            let mut v = [0.0f64; 6];
            for d in 0..D {
                v[d] = b.pose.velocity[d] as f64;
            }
            for k in 0..3 {
                v[3 + k] = b.pose.angular_velocity[k] as f64;
            }
            v
        }));
    }

    /// The faces between fluid cells and bodies' solid cells, in the order
    /// of the solid cells (after `mark_fluid`); then each body's velocity
    /// takes the hydrostatic correction of its faces' pressure over `dt`
    /// (module docs).
    pub(super) fn couple_bodies(
        &mut self,
        bodies: &[StepBody<D>],
        first: usize,
        (dt, rho, gravity): (f32, f32, &SVector<f32, D>),
    ) {
        self.body_faces.clear();
        if bodies.is_empty() {
            return;
        }
        let mut correction = vec![[0.0f64; 6]; bodies.len()];
        let half_cell = 0.5 * rho as f64 * (self.dx as f64).powi(D as i32);
        let (n, dx) = (self.n, self.dx);
        let stride_c = strides(&shape::<D>(n, None));
        for i in 0..self.solid_cells.len() {
            let s = self.solid_cells[i];
            let Some(b) = (self.solid[s] as usize - 1).checked_sub(first) else {
                continue;
            };
            let centre = &bodies[b].pose.center;
            let idx = self.unflat(s);
            for a in 0..D {
                for (other, sign, at) in [
                    (s - stride_c[a], 1.0f64, idx[a]),
                    (s + stride_c[a], -1.0, idx[a] + 1),
                ] {
                    let row = self.index[other];
                    if row == u32::MAX {
                        continue;
                    }
                    let mut r = [0.0f64; 3];
                    for d in 0..D {
                        let x = if d == a {
                            at as f32 * dx
                        } else {
                            (idx[d] as f32 + 0.5) * dx
                        };
                        r[d] = (x - centre[d]) as f64;
                    }
                    let mut e = [0.0f64; 3];
                    e[a] = 1.0;
                    let rxe = [
                        r[1] * e[2] - r[2] * e[1],
                        r[2] * e[0] - r[0] * e[2],
                        r[0] * e[1] - r[1] * e[0],
                    ];
                    let k = [e[0], e[1], e[2], rxe[0], rxe[1], rxe[2]];
                    // the fluid cell's pressure is half a cell from the face: `ρ·g·(x_f − x_c)`,
                    // `s·ρ·(dx/2)·g_a`, there; on the body, along `s·e_a`
                    let fa = half_cell * gravity[a] as f64;
                    for (c, kk) in correction[b].iter_mut().zip(&k) {
                        *c += fa * kk;
                    }
                    self.body_faces.push(BodyFace {
                        row,
                        body: b as u16,
                        j: k.map(|x| sign * x),
                    });
                }
            }
        }
        self.body_force = correction;
        for ((v, f), body) in self
            .body_velocity
            .iter_mut()
            .zip(&self.body_force)
            .zip(bodies)
        {
            let dv = body.apply_inverse(f);
            for k in 0..6 {
                v[k] += dt as f64 * dv[k];
            }
        }
    }

    /// Adds the bodies' part of the matrix's diagonal (`w·J_fᵀ M⁻¹ J_f`, `w = ρ·dx^D`) to `diag`.
    pub(super) fn body_diagonal(&self, bodies: &[StepBody<D>], w: f64, diag: &mut [f64]) {
        for f in &self.body_faces {
            diag[f.row as usize] += w * dot6(&f.j, &bodies[f.body as usize].apply_inverse(&f.j));
        }
    }

    /// `q += w·J M⁻¹ Jᵀ p` over the bodies; returns `p·(w·J M⁻¹ Jᵀ p)`. Serial, in face order.
    pub(super) fn body_apply(
        &self,
        bodies: &[StepBody<D>],
        w: f64,
        p: &[f64],
        q: &mut [f64],
    ) -> f64 {
        if self.body_faces.is_empty() {
            return 0.0;
        }
        let mut g = vec![[0.0f64; 6]; bodies.len()];
        for f in &self.body_faces {
            let pr = p[f.row as usize];
            let gb = &mut g[f.body as usize];
            for k in 0..6 {
                gb[k] += f.j[k] * pr;
            }
        }
        let y: Vec<[f64; 6]> = g
            .iter()
            .zip(bodies)
            .map(|(g, b)| b.apply_inverse(g).map(|x| w * x))
            .collect();
        let mut pq = 0.0;
        for f in &self.body_faces {
            let add = dot6(&f.j, &y[f.body as usize]);
            q[f.row as usize] += add;
            pq += p[f.row as usize] * add;
        }
        pq
    }

    /// After the solve: each body's impulse over the step (the pressure's and the hydrostatic
    /// correction's) and its velocity change, and the velocity its faces carry from now on (`V'`).
    pub(super) fn finish_bodies(&mut self, bodies: &[StepBody<D>], dt: f32) {
        self.body_steps.clear();
        self.body_steps.resize(bodies.len(), BodyStep::default());
        let area = (self.dx as f64).powi(D as i32 - 1) * dt as f64;
        let mut pressure = vec![[0.0f64; 6]; bodies.len()];
        for f in &self.body_faces {
            let pr = self.pressure[self.fluid[f.row as usize]];
            let s = &mut pressure[f.body as usize];
            for k in 0..6 {
                s[k] += area * f.j[k] * pr;
            }
        }
        for (b, body) in bodies.iter().enumerate() {
            let dv = body.apply_inverse(&pressure[b]);
            for k in 0..6 {
                self.body_velocity[b][k] += dv[k];
            }
            let s = &mut self.body_steps[b];
            s.impulse = std::array::from_fn(|k| pressure[b][k] + dt as f64 * self.body_force[b][k]);
            s.delta = body.apply_inverse(&s.impulse);
        }
    }

    /// What the last step did to each body (index as the step's bodies).
    pub fn body_steps(&self) -> &[BodyStep] {
        &self.body_steps
    }

    /// Body `b`'s velocity at `x` [m/s] in the step: `V*` before the solve, `V'` after it.
    pub(super) fn body_point_velocity(
        &self,
        bodies: &[StepBody<D>],
        b: usize,
        x: &SVector<f32, D>,
    ) -> SVector<f32, D> {
        let v = &self.body_velocity[b];
        let linear = SVector::from_fn(|d, _| v[d] as f32);
        let w = [v[3] as f32, v[4] as f32, v[5] as f32];
        point_velocity(&bodies[b].pose.center, &linear, &w, x)
    }
}

/// Puts each particle deeper than `depth` [m] inside a body of `poses` back
/// onto its surface, without its velocity into the body relative to the
/// body's point there, then within `(lo, hi)` on every axis; in parallel on
/// the calling pool, each particle its own.
pub fn push_out_of_bodies<const D: usize>(
    particles: &mut [Particle<D>],
    poses: &[BodyPose<D>],
    depth: f32,
    (lo, hi): (f32, f32),
) {
    if poses.is_empty() {
        return;
    }
    particles.par_chunks_mut(1024).for_each(|chunk| {
        for p in chunk {
            let mut moved = false;
            for pose in poses {
                if !pose.near(&p.x, 0.0, 0.0) {
                    continue;
                }
                let (phi, n) = pose.sdf_normal(&p.x);
                if phi >= -depth {
                    continue;
                }
                p.x -= n * phi;
                let rel = (p.v - pose.point_velocity(&p.x)).dot(&n);
                if rel < 0.0 {
                    p.v -= n * rel;
                }
                moved = true;
            }
            if moved {
                for d in 0..D {
                    p.x[d] = p.x[d].clamp(lo, hi);
                }
            }
        }
    });
}
