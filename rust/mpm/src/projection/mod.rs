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
//! tangential components inside a wall copy the fluid's next to it. The
//! step is bounded by advection only ([`Projection::steps_for`]).
//!
//! A step is the same bits whatever the threads: p2g runs in two parts of
//! the particles fixed by their count (`transfer.rs`), summed in one order;
//! g2p gives each particle its own; the pressure solve is serial, its sums
//! in f64, and starts from zero, so a step reads nothing but the particles.
//! It runs on the pool it is called in (the solver's:
//! `solver/large_step.rs`). `benchmarks/large_step.py`
//! holds the prototype this module follows and its checks (docs/large-step.md).

use nalgebra::SVector;
use rayon::prelude::*;

use crate::particles::Particle;
use transfer::{Kernel, Part, for_each_node, kinds};

mod transfer;

/// The volume correction's rate `κ` (per step, of the relative excess density).
pub const VOLUME_CORRECTION: f32 = 0.1;
/// The smallest fraction of a cell between a fluid cell's centre and the free surface.
pub const MIN_THETA: f32 = 0.05;
/// The Poisson solve stops at this residual, relative to the right-hand side's norm.
pub const CG_TOLERANCE: f64 = 1e-6;
/// The most CG iterations a step takes.
pub const CG_MAX_ITERATIONS: usize = 2000;
/// The advective CFL number: the fastest particle crosses at most this many cells a step.
pub const ADVECTIVE_CFL: f32 = 1.0;

/// What a projection step did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ProjectionStats {
    /// Fluid cells in the Poisson solve.
    pub fluid_cells: usize,
    /// CG iterations.
    pub iterations: usize,
    /// The residual's norm over the right-hand side's at the end.
    pub residual: f64,
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
    /// The two parts of the p2g ([`Part`]) and the cells holding a particle (scratch).
    parts: [Part; 2],
    marked: Vec<bool>,
}

/// Particles a g2p task takes at once.
const G2P_CHUNK: usize = 1024;

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

impl<const D: usize> Projection<D> {
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
            parts: Default::default(),
            marked: Vec::new(),
        }
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

    /// One step of `dt` [s] for water particles of rest density `rho` [kg/m³].
    pub fn step(
        &mut self,
        particles: &mut [Particle<D>],
        dt: f32,
        gravity: &SVector<f32, D>,
        rho: f32,
    ) -> ProjectionStats {
        self.step_advancing(particles, dt, dt, gravity, rho)
    }

    /// One step of `dt` [s] that moves the particles by `advance·v` [s] (a step spanning several
    /// frames moves them one frame's worth; the frames after it move them on at `v`).
    pub fn step_advancing(
        &mut self,
        particles: &mut [Particle<D>],
        dt: f32,
        advance: f32,
        gravity: &SVector<f32, D>,
        rho: f32,
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
        self.walls();
        self.mark_fluid(particles);
        let stats = self.solve(dt, rho);
        self.subtract_gradient(dt, rho);
        self.walls();
        self.g2p(particles, advance);
        stats
    }

    /// p2g in two fixed parts of the particles (in parallel on the calling
    /// pool), summed in one order; then the face velocities and each cell's
    /// smoothed density over `rho`.
    fn p2g(&mut self, particles: &[Particle<D>], dt: f32, rho: f32) {
        let (n, dx) = (self.n, self.dx);
        let (first, second) = particles.split_at(particles.len() / 2);
        let (p0, p1) = self.parts.split_at_mut(1);
        rayon::join(
            || p0[0].scatter(first, n, dx, dt),
            || p1[0].scatter(second, n, dx, dt),
        );
        let (p0, p1) = (&self.parts[0], &self.parts[1]);
        for a in 0..D {
            let (vel, mass) = (&mut self.vel[a], &mut self.mass[a]);
            for (i, (f0, f1)) in p0.faces[a].iter().zip(&p1.faces[a]).enumerate() {
                let m = f0[0] + f1[0];
                mass[i] = m;
                vel[i] = if m > 0.0 { (f0[1] + f1[1]) / m } else { 0.0 };
            }
        }
        let scale = 1.0 / (dx.powi(D as i32) * rho);
        for (c, d) in self.density.iter_mut().enumerate() {
            *d = (p0.cell[c] + p1.cell[c]) * scale;
        }
    }

    /// Free slip: zero the normal faces in and on the walls; inside a wall the tangential components copy the fluid's.
    fn walls(&mut self) {
        let (n, ws) = (self.n, self.ws);
        for a in 0..D {
            let s = shape::<D>(n, Some(a));
            let stride = strides(&s);
            let vel = &mut self.vel[a];
            for_each_node(&s, |flat, idx| {
                if idx[a] <= ws || idx[a] >= n - ws {
                    vel[flat] = 0.0;
                    return;
                }
                // the nearest face inside the fluid region along each tangential axis
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
            });
        }
    }

    fn is_solid(&self, idx: &[usize; D]) -> bool {
        idx.iter().any(|&i| i < self.ws || i >= self.n - self.ws)
    }

    /// The fluid cells: those holding a particle, away from the walls.
    fn mark_fluid(&mut self, particles: &[Particle<D>]) {
        let (n, dx) = (self.n, self.dx);
        let stride = strides(&shape::<D>(n, None));
        self.index.fill(u32::MAX);
        let mut marked = std::mem::take(&mut self.marked);
        marked.clear();
        marked.resize(self.index.len(), false);
        for p in particles {
            let idx: [usize; D] = std::array::from_fn(|d| ((p.x[d] / dx) as usize).min(n - 1));
            if !self.is_solid(&idx) {
                marked[(0..D).map(|d| idx[d] * stride[d]).sum::<usize>()] = true;
            }
        }
        self.fluid.clear();
        for (c, m) in marked.iter().enumerate() {
            if *m {
                self.index[c] = self.fluid.len() as u32;
                self.fluid.push(c);
            }
        }
        self.marked = marked;
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
                if !self.is_solid(&j) {
                    out[k] = if up { c + stride[a] } else { c - stride[a] };
                }
            }
        }
        out
    }

    fn solve(&mut self, dt: f32, rho: f32) -> ProjectionStats {
        let m = self.fluid.len();
        let (n, dx) = (self.n, self.dx);
        // the matrix: per row the diagonal and up to 2·D fluid neighbours
        let mut diag = vec![0.0f64; m];
        let mut nbr = vec![[u32::MAX; 6]; m];
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
            div -= VOLUME_CORRECTION * (self.density[c] - 1.0).max(0.0) / dt;
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
        // from zero, not the last step's pressure: a step reads nothing but the particles (a restored
        // checkpoint steps the same bits)
        let mut x = vec![0.0f64; m];
        let apply = |v: &[f64], out: &mut [f64]| {
            for r in 0..m {
                let mut s = diag[r] * v[r];
                for &k in &nbr[r][..2 * D] {
                    if k != u32::MAX {
                        s -= v[k as usize];
                    }
                }
                out[r] = s;
            }
        };
        let dot = |u: &[f64], v: &[f64]| u.iter().zip(v).map(|(a, b)| a * b).sum::<f64>();
        let mut r = vec![0.0; m];
        apply(&x, &mut r);
        for i in 0..m {
            r[i] = b[i] - r[i];
        }
        let bnorm = dot(&b, &b).sqrt().max(1e-300);
        let mut z: Vec<f64> = r.iter().zip(&diag).map(|(r, d)| r / d.max(1.0)).collect();
        let mut p = z.clone();
        let mut q = vec![0.0; m];
        let mut rz = dot(&r, &z);
        let mut iterations = 0;
        let mut residual = dot(&r, &r).sqrt() / bnorm;
        while residual > CG_TOLERANCE && iterations < CG_MAX_ITERATIONS {
            apply(&p, &mut q);
            let alpha = rz / dot(&p, &q);
            for i in 0..m {
                x[i] += alpha * p[i];
                r[i] -= alpha * q[i];
            }
            for i in 0..m {
                z[i] = r[i] / diag[i].max(1.0);
            }
            let rz_new = dot(&r, &z);
            let beta = rz_new / rz;
            rz = rz_new;
            for i in 0..m {
                p[i] = z[i] + beta * p[i];
            }
            iterations += 1;
            residual = dot(&r, &r).sqrt() / bnorm;
        }
        self.pressure.iter_mut().for_each(|v| *v = 0.0);
        for (k, &c) in self.fluid.iter().enumerate() {
            self.pressure[c] = x[k];
        }
        ProjectionStats {
            fluid_cells: m,
            iterations,
            residual,
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
                } else if !self.is_solid(&lo_idx) {
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
                if self.index[hi] == u32::MAX && !self.is_solid(&hi_idx) {
                    self.vel[a][low_face + st[a]] -= k * (-pc / self.theta(c, hi));
                }
            }
        }
    }

    /// The particles move on at their velocity for `dt` [s], kept inside the walls as g2p keeps them
    /// (a frame inside a step that spans several).
    pub fn drift(&self, particles: &mut [Particle<D>], dt: f32) {
        let lo = (self.ws as f32 + 1e-3) * self.dx;
        let hi = 1.0 - lo;
        for p in particles.iter_mut() {
            for d in 0..D {
                p.x[d] = (p.x[d] + dt * p.v[d]).clamp(lo, hi);
            }
        }
    }

    /// g2p (APIC) and the move, per particle: in parallel on the calling pool, each particle its own.
    fn g2p(&mut self, particles: &mut [Particle<D>], dt: f32) {
        let (n, dx) = (self.n, self.dx);
        let apic = 4.0 / (dx * dx);
        let st_f: [[usize; D]; D] = std::array::from_fn(|a| strides(&shape::<D>(n, Some(a))));
        let lo = (self.ws as f32 + 1e-3) * dx;
        let hi = 1.0 - lo;
        let vel = &self.vel;
        particles.par_chunks_mut(G2P_CHUNK).for_each(|chunk| {
            for p in chunk {
                let k = Kernel::new(&p.x, dx, n);
                for a in 0..D {
                    let (va, ca) = k.gather(kinds(Some(a)), &st_f[a], &vel[a]);
                    p.v[a] = va;
                    for d in 0..D {
                        p.c[(a, d)] = apic * ca[d];
                    }
                }
                for d in 0..D {
                    p.x[d] = (p.x[d] + dt * p.v[d]).clamp(lo, hi);
                }
            }
        });
    }
}

#[cfg(test)]
mod tests;
