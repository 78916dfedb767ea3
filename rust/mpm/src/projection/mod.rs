//! Incompressible APIC water with a pressure projection: the large step.
//!
//! Per step (Jiang et al. 2015, "The affine particle-in-cell method", on a
//! MAC grid; Bridson, *Fluid Simulation for Computer Graphics*, 2nd ed.):
//!
//! 1. p2g: each velocity component lives on its own face grid (component
//!    `a` at `(i + ½ − ½·e_a)·dx`); a particle spreads its mass and its
//!    affine momentum `m·(v_a + c_a·(x_i − x_p))` there with quadratic
//!    B-spline weights (`crate::kernel::quadratic_weights`), its external acceleration as
//!    momentum `m·a·dt`;
//! 2. gravity on the face velocities;
//! 3. the projection: the cells holding a particle (away from the walls) are
//!    fluid; the pressure `p` on them solves the Poisson equation
//!    `−∇²p = −(ρ/dt)·(∇·u − κ·max(ρ_c/ρ₀ − 1, 0)/dt)` with `p = 0` at the
//!    free surface, placed where the particles' smoothed density crosses ½
//!    between a fluid cell and its air neighbour (ghost fluid, second order:
//!    Gibou et al. 2002, Enright et al. 2003), and no flow through the walls;
//!    `κ` is the volume correction (after Kugelstadt et al. 2019) that asks
//!    a cell denser than rest to spread; then `u ← u − (dt/ρ)·∇p`;
//! 4. g2p: `v_a = Σ w u_a`, `c_a = (4/dx²)·Σ w u_a (x_i − x_p)` (APIC), and
//!    `x ← x + dt·v`, kept inside the walls.
//!
//! The box walls are free slip: no normal flow through a wall face, and the
//! tangential components inside a wall copy the fluid's next to it.
//! Colliders, at rest or moving, are solid cells with their own velocity
//! (`obstacles.rs`). The step is bounded by advection only
//! ([`Projection::steps_for`]).
//!
//! A step is the same bits whatever the threads: p2g runs in two parts of
//! the particles fixed by their count (`transfer.rs`), summed in one order;
//! g2p gives each particle its own; the pressure solve is serial, its sums
//! in f64, and starts from zero, so a step reads nothing but the particles.
//! The transfers run in the compiled copy the solver chose ([`crate::isa`]:
//! the x86-64-v3 one where the CPU has it; the same bits either way).
//! It runs on the pool it is called in (the solver's:
//! `solver/large_step.rs`). `benchmarks/large_step.py`
//! holds the prototype this module follows and its checks (docs/large-step.md).

use nalgebra::{SMatrix, SVector};
use rayon::prelude::*;

use crate::collider::PROJECT_DEPTH_CELLS;
use crate::isa::Isa;
use crate::particles::Particle;
pub use bodies::{BodyStep, StepBody, push_out_of_bodies};
pub use obstacles::StepColliders;
use transfer::{Part, for_each_node, g2p_chunk};

mod bodies;
mod obstacles;
mod precond;
mod transfer;

/// The volume correction's rate `κ` (per step, of the relative excess density).
pub const VOLUME_CORRECTION: f32 = 0.1;
/// The smallest fraction of a cell between a fluid cell's centre and the free surface.
pub const MIN_THETA: f32 = 0.05;
/// The Poisson solve stops at this residual, relative to the right-hand side's norm.
pub const CG_TOLERANCE: f64 = 1e-6;
/// The most CG iterations a step takes.
pub const CG_MAX_ITERATIONS: usize = 2000;
/// The advective CFL number: the fastest particle crosses at most this many cells a step. Two cells
/// take a quarter fewer steps than one on the 3D dam break and keep every accuracy check
/// (docs/large-step.md: Martin & Moyce on 128², 64² and 34³, the column at rest, the first sloshing
/// mode); three bring the 64² column's height to the edge of its tolerance.
pub const ADVECTIVE_CFL: f32 = 2.0;

/// What a projection step did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ProjectionStats {
    /// Fluid cells in the Poisson solve.
    pub fluid_cells: usize,
    /// CG iterations.
    pub iterations: usize,
    /// The residual's norm over the right-hand side's at the end.
    pub residual: f64,
    /// Where the step stopped before moving the particles: the bound on their speed [m/s] its solved
    /// velocity gives, which would carry them farther than the travel limit in the step
    /// ([`Projection::set_travel_limit`]).
    pub stopped: Option<f32>,
}

/// The grids of the projection step on the unit box: `n` cells a side,
/// walls `ws` cells thick on every face (the fluid rests on the face
/// `ws·dx`, as the explicit engine's water rests on `(walls.cells − 1)·dx`).
#[derive(Clone, Debug)]
pub struct Projection<const D: usize> {
    n: usize,
    ws: usize,
    dx: f32,
    /// Per component: face velocities [m/s] and masses [kg].
    vel: Vec<Vec<f32>>,
    mass: Vec<Vec<f32>>,
    /// Per cell: smoothed density over the rest density, fluid index (`u32::MAX`: not fluid), pressure [Pa].
    density: Vec<f32>,
    index: Vec<u32>,
    pressure: Vec<f64>,
    fluid: Vec<usize>,
    /// Per cell: the collider whose solid cell it is (index + 1; 0: none), the solid cells, and each
    /// collider's velocity [m/s] in the step (`obstacles.rs`).
    solid: Vec<u16>,
    solid_cells: Vec<usize>,
    obstacle_velocity: Vec<SVector<f32, D>>,
    /// The faces between fluid cells and bodies' solid cells, each body's velocity in the step
    /// (`[v, ω]`) and what the step did to it (`bodies.rs`).
    body_faces: Vec<bodies::BodyFace>,
    body_velocity: Vec<[f64; 6]>,
    body_force: Vec<[f64; 6]>,
    body_steps: Vec<BodyStep>,
    /// The two parts of the p2g ([`Part`]).
    parts: [Part; 2],
    /// The compiled copy of the transfers that runs ([`crate::isa`]; the same bits either way).
    isa: Isa,
    /// The volume correction's time scale [s] when it is longer than the step
    /// ([`Projection::set_correction_time`]; 0: the step's own).
    correction_time: f32,
    /// The farthest [m] a step's solved velocity may carry a particle (infinite: no limit).
    travel_limit: f32,
}

/// Particles a g2p task takes at once.
const G2P_CHUNK: usize = 1024;
/// The most particles a drift frame moves on one thread.
const DRIFT_SERIAL: usize = 16 * G2P_CHUNK;
/// Faces or cells a task of the p2g's sum takes at once.
const MERGE_CHUNK: usize = 8192;

/// A face grid's shape: `n` cells a side, `n + 1` nodes along `axis` (`None`: the cell centres).
fn shape<const D: usize>(n: usize, axis: Option<usize>) -> [usize; D] {
    std::array::from_fn(|d| n + usize::from(Some(d) == axis))
}

fn strides<const D: usize>(s: &[usize; D]) -> [usize; D] {
    let mut st = [1usize; D];
    for d in (0..D.saturating_sub(1)).rev() {
        st[d] = st[d + 1] * s[d + 1];
    }
    st
}

/// The wall condition on one face of component `a` (flat index `flat`, index `idx`): zero in and on the
/// walls along `a`; a face inside a wall along another axis copies the nearest face inside the fluid region.
#[inline(always)]
fn wall_face<const D: usize>(
    vel: &mut [f32],
    a: usize,
    n: usize,
    ws: usize,
    stride: &[usize; D],
    flat: usize,
    idx: &[usize; D],
) {
    if idx[a] <= ws || idx[a] >= n - ws {
        vel[flat] = 0.0;
        return;
    }
    let mut src = flat;
    for b in 0..D {
        if b != a {
            let j = idx[b].clamp(ws, n - ws - 1);
            src = src - idx[b] * stride[b] + j * stride[b];
        }
    }
    if src != flat {
        vel[flat] = vel[src];
    }
}

/// The grid's geometry the transfers read: `n` cells a side of `dx` [m], walls `ws` cells thick.
#[derive(Clone, Copy, Debug)]
pub(super) struct Grid {
    pub(super) n: usize,
    pub(super) ws: usize,
    pub(super) dx: f32,
}

impl Grid {
    /// Whether cell `idx` lies in the walls.
    #[inline(always)]
    pub(super) fn in_walls<const D: usize>(&self, idx: &[usize; D]) -> bool {
        idx.iter().any(|&i| i < self.ws || i >= self.n - self.ws)
    }

    /// The bounds [m] a particle is kept within on every axis: a thousandth of a cell inside the walls' faces.
    #[inline(always)]
    pub(super) fn inside(&self) -> (f32, f32) {
        let lo = (self.ws as f32 + 1e-3) * self.dx;
        (lo, 1.0 - lo)
    }
}

impl<const D: usize> Projection<D> {
    /// The grid's geometry.
    fn grid(&self) -> Grid {
        Grid {
            n: self.n,
            ws: self.ws,
            dx: self.dx,
        }
    }

    /// The grids for `n_grid` cells a side and walls of `wall_cells` nodes (the engine's `walls.cells`, at least 2).
    pub fn new(n_grid: usize, wall_cells: usize) -> Self {
        let n = n_grid;
        let cells = n.pow(D as u32);
        Projection {
            n,
            ws: wall_cells.max(2) - 1,
            dx: 1.0 / n as f32,
            vel: (0..D)
                .map(|a| vec![0.0; shape::<D>(n, Some(a)).iter().product()])
                .collect(),
            mass: (0..D)
                .map(|a| vec![0.0; shape::<D>(n, Some(a)).iter().product()])
                .collect(),
            density: vec![0.0; cells],
            index: vec![u32::MAX; cells],
            pressure: vec![0.0; cells],
            fluid: Vec::new(),
            solid: vec![0; cells],
            solid_cells: Vec::new(),
            obstacle_velocity: Vec::new(),
            body_faces: Vec::new(),
            body_velocity: Vec::new(),
            body_force: Vec::new(),
            body_steps: Vec::new(),
            parts: Default::default(),
            isa: Isa::detect(),
            correction_time: 0.0,
            travel_limit: f32::INFINITY,
        }
    }

    /// The volume correction spreads a cell denser than rest by `κ·(ρ/ρ₀ − 1)` cells over
    /// `max(dt, t)` rather than over each step `dt` (`t` [s]: the frame; 0, the default: every
    /// step). Per step, the correction's velocity `κ·(ρ/ρ₀ − 1)·dx/dt` grows as the step shrinks,
    /// so a frame of `n` steps spread compressed water `n` times as far, and faster: the more
    /// steps a violent frame took, the harder it pushed, until a frame could not be finished
    /// (`paddle3d` dragged at 50 m/s, after 4,643 frames). Over the frame, water relaxes at `κ`
    /// a frame however many steps it takes; a step spanning frames is unchanged.
    pub fn set_correction_time(&mut self, t: f32) {
        self.correction_time = t;
    }

    /// A step stops before it moves the particles where its solved velocity would carry one farther
    /// than `limit` [m] in the step (`ProjectionStats::stopped`, with the particles and the bodies as
    /// they were): the caller steps again with a shorter `dt`. The bound on a particle's speed is
    /// the norm of the largest face speed along each axis over the faces of the fluid cells, where
    /// the solve changed the velocity (a particle's velocity interpolates the faces with positive
    /// weights). Infinite, the default: no limit.
    pub fn set_travel_limit(&mut self, limit: f32) {
        self.travel_limit = limit;
    }

    /// Runs the transfers with `isa` ([`crate::Solver::set_isa`] passes its choice on). Call it only
    /// with a variant the CPU has ([`Isa::available`]).
    pub fn set_isa(&mut self, isa: Isa) {
        self.isa = isa;
    }

    /// The bounds [m] the step keeps a particle within on every axis (a thousandth of a cell inside
    /// the walls' faces).
    pub fn bounds(&self) -> (f32, f32) {
        self.grid().inside()
    }

    /// The cell pressures [Pa] of the last step, row-major (`x` slowest), 0 off the fluid.
    pub fn pressure(&self) -> &[f64] {
        &self.pressure
    }

    /// Steps that advance `dt_frame` [s] at the advective CFL: `⌈dt_frame / dt⌉` with
    /// `dt = cfl·dx / (|v|max + √(|g|·dx))`.
    pub fn steps_for(
        &self,
        particles: &[Particle<D>],
        gravity: &SVector<f32, D>,
        dt_frame: f32,
    ) -> usize {
        let vmax = particles.iter().map(|p| p.v.amax()).fold(0.0f32, f32::max);
        let dt = ADVECTIVE_CFL * self.dx / (vmax + (gravity.norm() * self.dx).sqrt());
        ((dt_frame / dt - 1e-6).ceil() as usize).max(1)
    }

    /// One step of `dt` [s] for water particles of rest density `rho` [kg/m³] in the box walls.
    pub fn step(
        &mut self,
        particles: &mut [Particle<D>],
        dt: f32,
        gravity: &SVector<f32, D>,
        rho: f32,
    ) -> ProjectionStats {
        self.step_advancing(particles, dt, dt, gravity, rho, &StepColliders::none())
    }

    /// One step of `dt` [s] that moves the particles by `advance·v` [s] (a step spanning several
    /// frames moves them one frame's worth; the frames after it move them on at `v`), with the
    /// colliders `cols` at their poses for the step as solid cells (`obstacles.rs`) and its bodies
    /// coupled in the solve (`bodies.rs`; what it did to them: [`Projection::body_steps`]).
    pub fn step_advancing(
        &mut self,
        particles: &mut [Particle<D>],
        dt: f32,
        advance: f32,
        gravity: &SVector<f32, D>,
        rho: f32,
        cols: &StepColliders<'_, D>,
    ) -> ProjectionStats {
        self.p2g(particles, dt, rho);
        for a in 0..D {
            if gravity[a] != 0.0 {
                for (u, m) in self.vel[a].iter_mut().zip(&self.mass[a]) {
                    if *m > 0.0 {
                        *u += dt * gravity[a];
                    }
                }
            }
        }
        self.mark_solid(cols);
        self.mark_fluid();
        self.start_bodies(cols.bodies);
        self.couple_bodies(cols.bodies, cols.colliders.len(), (dt, rho, gravity));
        self.walls();
        self.obstacle_faces(cols, false);
        let stats = self.solve(dt, rho, cols.bodies);
        self.subtract_gradient(dt, rho);
        self.walls();
        if self.travel_limit.is_finite() {
            let bound = self.fluid_face_speed();
            if bound * dt > self.travel_limit {
                return ProjectionStats {
                    stopped: Some(bound),
                    ..stats
                };
            }
        }
        self.finish_bodies(cols.bodies, dt);
        self.obstacle_faces(cols, true);
        self.g2p(particles, advance, cols);
        stats
    }

    /// The norm of the largest face speed along each axis over the faces of the fluid cells [m/s].
    fn fluid_face_speed(&self) -> f32 {
        let n = self.n;
        let st: [[usize; D]; D] = std::array::from_fn(|a| strides(&shape::<D>(n, Some(a))));
        let mut top = [0.0f32; D];
        for &c in &self.fluid {
            let idx = self.unflat(c);
            for a in 0..D {
                let low: usize = (0..D).map(|d| idx[d] * st[a][d]).sum();
                top[a] = top[a]
                    .max(self.vel[a][low].abs())
                    .max(self.vel[a][low + st[a][a]].abs());
            }
        }
        top.iter().map(|t| t * t).sum::<f32>().sqrt()
    }

    /// p2g in two fixed parts of the particles (in parallel on the calling
    /// pool), summed in one order; then the face velocities and each cell's
    /// smoothed density over `rho`.
    fn p2g(&mut self, particles: &[Particle<D>], dt: f32, rho: f32) {
        let (g, isa) = (self.grid(), self.isa);
        let (first, second) = particles.split_at(particles.len() / 2);
        let (p0, p1) = self.parts.split_at_mut(1);
        rayon::join(
            || p0[0].scatter(isa, first, g, dt),
            || p1[0].scatter(isa, second, g, dt),
        );
        // the sums, face by face (in parallel: each face its own)
        let (p0, p1) = (&self.parts[0], &self.parts[1]);
        for a in 0..D {
            let (f0, f1) = (&p0.faces[a], &p1.faces[a]);
            self.vel[a]
                .par_chunks_mut(MERGE_CHUNK)
                .zip(self.mass[a].par_chunks_mut(MERGE_CHUNK))
                .enumerate()
                .for_each(|(k, (vel, mass))| {
                    let at = k * MERGE_CHUNK;
                    for i in 0..vel.len() {
                        let (g0, g1) = (f0[at + i], f1[at + i]);
                        let m = g0[0] + g1[0];
                        mass[i] = m;
                        vel[i] = if m > 0.0 { (g0[1] + g1[1]) / m } else { 0.0 };
                    }
                });
        }
        let scale = 1.0 / (g.dx.powi(D as i32) * rho);
        let (c0, c1) = (&p0.cell, &p1.cell);
        self.density
            .par_chunks_mut(MERGE_CHUNK)
            .enumerate()
            .for_each(|(k, d)| {
                let at = k * MERGE_CHUNK;
                for (i, d) in d.iter_mut().enumerate() {
                    *d = (c0[at + i] + c1[at + i]) * scale;
                }
            });
    }

    /// Free slip: zero the normal faces in and on the walls; inside a wall the tangential components copy the fluid's.
    /// Only the faces in the walls' band are visited: a row of the last axis away from the walls has its
    /// two ends in the band, the rest of it is left as it is.
    fn walls(&mut self) {
        let (n, ws) = (self.n, self.ws);
        for a in 0..D {
            let s = shape::<D>(n, Some(a));
            let stride = strides(&s);
            let vel = &mut self.vel[a];
            // the band of an axis: below `lo[d]` or above `hi[d]` (the normal axis zeroes in and on the
            // walls, a tangential axis copies the fluid's inside them)
            let lo: [usize; D] = std::array::from_fn(|d| if d == a { ws + 1 } else { ws });
            let hi = [n - ws - 1; D];
            let last = D - 1;
            let rows: [usize; D] = std::array::from_fn(|d| if d == last { 1 } else { s[d] });
            for_each_node(&rows, |_, outer| {
                let start: usize = (0..last).map(|d| outer[d] * stride[d]).sum();
                let interior = (0..last).all(|d| outer[d] >= lo[d] && outer[d] <= hi[d]);
                let mut idx = *outer;
                let mut visit = |k: usize| {
                    idx[last] = k;
                    wall_face(vel, a, n, ws, &stride, start + k, &idx);
                };
                if interior {
                    (0..lo[last]).for_each(&mut visit);
                    (hi[last] + 1..s[last]).for_each(&mut visit);
                } else {
                    (0..s[last]).for_each(&mut visit);
                }
            });
        }
    }

    /// Whether cell `c` (index `idx`) is solid: a wall's or a collider's.
    fn is_solid(&self, idx: &[usize; D], c: usize) -> bool {
        self.grid().in_walls(idx) || self.in_obstacle(c)
    }

    /// The fluid cells: those holding a particle, away from the walls (the p2g's parts found them) and
    /// the colliders.
    fn mark_fluid(&mut self) {
        self.index.fill(u32::MAX);
        self.fluid.clear();
        let (h0, h1) = (&self.parts[0].held, &self.parts[1].held);
        for (c, (a, b)) in h0.iter().zip(h1).enumerate() {
            if (*a || *b) && self.solid[c] == 0 {
                self.index[c] = self.fluid.len() as u32;
                self.fluid.push(c);
            }
        }
    }

    fn unflat(&self, c: usize) -> [usize; D] {
        let stride = strides(&shape::<D>(self.n, None));
        let mut r = c;
        std::array::from_fn(|d| {
            let i = r / stride[d];
            r %= stride[d];
            i
        })
    }

    /// Where the surface lies between fluid cell `f` and air cell `air`, as a fraction of dx.
    fn theta(&self, f: usize, air: usize) -> f32 {
        let (df, da) = (self.density[f], self.density[air]);
        ((df - 0.5) / (df - da).max(1e-6)).clamp(MIN_THETA, 1.0)
    }

    /// Per fluid cell: its 2·D neighbours (cell index, or `usize::MAX` for a wall) and the diagonal.
    fn neighbours(&self, c: usize) -> [usize; 6] {
        let stride = strides(&shape::<D>(self.n, None));
        let idx = self.unflat(c);
        let mut out = [usize::MAX; 6];
        for a in 0..D {
            for (k, up) in [(2 * a, true), (2 * a + 1, false)] {
                let mut j = idx;
                j[a] = if up { idx[a] + 1 } else { idx[a] - 1 };
                let nb = if up { c + stride[a] } else { c - stride[a] };
                if !self.is_solid(&j, nb) {
                    out[k] = nb;
                }
            }
        }
        out
    }

    fn solve(&mut self, dt: f32, rho: f32, bodies: &[StepBody<D>]) -> ProjectionStats {
        let m = self.fluid.len();
        let tc = if self.correction_time > dt {
            self.correction_time
        } else {
            dt
        };
        let (n, dx) = (self.n, self.dx);
        // the matrix: per row the diagonal and up to 2·D fluid neighbours
        let mut diag = vec![0.0f64; m];
        // a missing neighbour reads the zero kept past the end of the vector the matrix is applied to
        // (`s − 0.0` is `s`: the same bits as skipping it)
        let mut nbr = vec![[m as u32; 6]; m];
        let mut b = vec![0.0f64; m];
        for (r, &c) in self.fluid.iter().enumerate() {
            let idx = self.unflat(c);
            let mut div = 0.0f32;
            for a in 0..D {
                let s = shape::<D>(n, Some(a));
                let st = strides(&s);
                let lo: usize = (0..D).map(|d| idx[d] * st[d]).sum();
                div += self.vel[a][lo + st[a]] - self.vel[a][lo];
            }
            div /= dx;
            div -= VOLUME_CORRECTION * (self.density[c] - 1.0).max(0.0) / tc;
            b[r] = -(rho as f64) * (dx as f64) * (dx as f64) / dt as f64 * div as f64;
            for (k, &nb) in self.neighbours(c).iter().enumerate().take(2 * D) {
                if nb == usize::MAX {
                    continue;
                }
                if self.index[nb] != u32::MAX {
                    diag[r] += 1.0;
                    nbr[r][k] = self.index[nb];
                } else {
                    diag[r] += 1.0 / self.theta(c, nb) as f64;
                }
            }
        }
        // the bodies' part, `w·J M⁻¹ Jᵀ` (`bodies.rs`), with its diagonal in the preconditioner
        let w = rho as f64 * (dx as f64).powi(D as i32);
        let mut pre_diag = diag.clone();
        self.body_diagonal(bodies, w, &mut pre_diag);
        pre_diag.iter_mut().for_each(|d| *d = d.max(1.0));
        let precon = precond::mic0(&pre_diag, &nbr, D);
        // CG (MIC(0)-preconditioned, `precond.rs`) from zero, not the last step's pressure: a step
        // reads nothing but the particles (a restored checkpoint steps the same bits). Every sum runs
        // in row order.
        let mut x = vec![0.0f64; m];
        let mut r = b.clone(); // b − A·0
        let bnorm = b.iter().map(|v| v * v).sum::<f64>().sqrt().max(1e-300);
        let (mut z, mut scratch) = (vec![0.0f64; m], vec![0.0f64; m]);
        precond::apply(&precon, &nbr, D, &r, &mut scratch, &mut z);
        let mut p = z.clone();
        p.push(0.0);
        let mut q = vec![0.0; m];
        let mut rz = r.iter().zip(&z).map(|(a, b)| a * b).sum::<f64>();
        let mut iterations = 0;
        let mut residual = r.iter().map(|v| v * v).sum::<f64>().sqrt() / bnorm;
        while residual > CG_TOLERANCE && iterations < CG_MAX_ITERATIONS {
            // q = A·p and p·q in one pass
            let mut pq = 0.0f64;
            for (row, (qr, (nb, d))) in q.iter_mut().zip(nbr.iter().zip(&diag)).enumerate() {
                let mut s = d * p[row];
                for &k in &nb[..2 * D] {
                    s -= p[k as usize];
                }
                *qr = s;
                pq += p[row] * s;
            }
            pq += self.body_apply(bodies, w, &p, &mut q);
            let alpha = rz / pq;
            let (mut rz_new, mut rr) = (0.0f64, 0.0f64);
            for i in 0..m {
                x[i] += alpha * p[i];
                r[i] -= alpha * q[i];
                rr += r[i] * r[i];
            }
            precond::apply(&precon, &nbr, D, &r, &mut scratch, &mut z);
            for i in 0..m {
                rz_new += r[i] * z[i];
            }
            let beta = rz_new / rz;
            rz = rz_new;
            for i in 0..m {
                p[i] = z[i] + beta * p[i];
            }
            iterations += 1;
            residual = rr.sqrt() / bnorm;
        }
        self.pressure.iter_mut().for_each(|v| *v = 0.0);
        for (k, &c) in self.fluid.iter().enumerate() {
            self.pressure[c] = x[k];
        }
        ProjectionStats {
            fluid_cells: m,
            iterations,
            residual,
            stopped: None,
        }
    }

    /// `u ← u − (dt/ρ)·∇p` on every face beside a fluid cell (the ghost pressure on a face to the air);
    /// the faces beside a wall keep what the wall condition sets.
    fn subtract_gradient(&mut self, dt: f32, rho: f32) {
        let n = self.n;
        let stride_c = strides(&shape::<D>(n, None));
        let k = dt / (rho * self.dx);
        for a in 0..D {
            let st = strides(&shape::<D>(n, Some(a)));
            for &c in &self.fluid {
                let idx = self.unflat(c);
                let low_face: usize = (0..D).map(|d| idx[d] * st[d]).sum();
                let pc = self.pressure[c] as f32;
                // the face between c − e_a and c
                let lo = c - stride_c[a];
                let mut lo_idx = idx;
                lo_idx[a] -= 1;
                let grad_dx = if self.index[lo] != u32::MAX {
                    Some(pc - self.pressure[lo] as f32)
                } else if !self.is_solid(&lo_idx, lo) {
                    Some(pc / self.theta(c, lo))
                } else {
                    None
                };
                if let Some(g) = grad_dx {
                    self.vel[a][low_face] -= k * g;
                }
                // the face between c and c + e_a, when c + e_a is air (a fluid neighbour has it as its low face)
                let hi = c + stride_c[a];
                let mut hi_idx = idx;
                hi_idx[a] += 1;
                if self.index[hi] == u32::MAX && !self.is_solid(&hi_idx, hi) {
                    self.vel[a][low_face + st[a]] -= k * (-pc / self.theta(c, hi));
                }
            }
        }
    }

    /// The particles move on at their velocity for `dt` [s], kept inside the walls as g2p keeps them
    /// and out of the colliders `cols` (a frame inside a step that spans several); returns the fastest
    /// one's speed [m/s].
    pub fn drift(
        &self,
        particles: &mut [Particle<D>],
        dt: f32,
        cols: &StepColliders<'_, D>,
    ) -> f32 {
        let (bounds, projecting) = (self.grid().inside(), cols.projecting(self.dx));
        // in parallel on the calling pool past a few chunks (fewer take longer to hand out than to
        // move): each particle its own, and the fastest speed is the same whichever way the chunks'
        // maxima combine
        if particles.len() <= DRIFT_SERIAL {
            return obstacles::drift_chunk(particles, dt, bounds, &projecting);
        }
        particles
            .par_chunks_mut(G2P_CHUNK)
            .map(|chunk| obstacles::drift_chunk(chunk, dt, bounds, &projecting))
            .reduce(|| 0.0, f32::max)
    }

    /// g2p (APIC) and the move, per particle, then out of the colliders: in parallel on the calling
    /// pool, each particle its own.
    fn g2p(&mut self, particles: &mut [Particle<D>], dt: f32, cols: &StepColliders<'_, D>) {
        let (g, isa, vel) = (self.grid(), self.isa, &self.vel);
        let (bounds, projecting) = (g.inside(), cols.projecting(g.dx));
        let (solid, moving, shapes) = (&self.solid, &self.obstacle_velocity, cols.colliders);
        let colliders = shapes.len();
        let stride = strides(&shape::<D>(self.n, None));
        let (n, dx) = (self.n, self.dx);
        let deep = 2.0 * PROJECT_DEPTH_CELLS * dx;
        particles.par_chunks_mut(G2P_CHUNK).for_each(|chunk| {
            // a particle deeper inside an obstacle than its projection reaches, in its cells (a fast
            // obstacle overtook it), is in no fluid cell, so its velocity was never projected: it
            // moves with the obstacle until the projection below can put it back on the surface,
            // rather than reading back the faces its own p2g set
            let inside: Vec<(usize, SVector<f32, D>, usize)> = if colliders == 0 {
                Vec::new()
            } else {
                chunk
                    .iter()
                    .enumerate()
                    .filter_map(|(i, p)| {
                        let c: usize = (0..D)
                            .map(|d| ((p.x[d] / dx) as usize).min(n - 1) * stride[d])
                            .sum();
                        let k = solid[c] as usize;
                        (k >= 1 && k <= colliders && shapes[k - 1].shape.sdf(&p.x) < -deep)
                            .then_some((i, p.x, k - 1))
                    })
                    .collect()
            };
            g2p_chunk(isa, chunk, vel, g, dt);
            for (i, x, k) in inside {
                let p = &mut chunk[i];
                p.v = moving[k];
                p.c = SMatrix::zeros();
                for d in 0..D {
                    p.x[d] = (x[d] + dt * p.v[d]).clamp(bounds.0, bounds.1);
                }
            }
            if !projecting.is_empty() {
                chunk
                    .iter_mut()
                    .for_each(|p| obstacles::project(&projecting, p, bounds));
            }
        });
    }
}

#[cfg(test)]
mod tests;
