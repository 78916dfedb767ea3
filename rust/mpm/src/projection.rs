//! Incompressible APIC water with a pressure projection: the large step.
//!
//! Per step (Jiang et al. 2015, "The affine particle-in-cell method", on a
//! MAC grid; Bridson, *Fluid Simulation for Computer Graphics*, 2nd ed.):
//!
//! 1. p2g: each velocity component lives on its own face grid (component
//!    `a` at `(i + ½ − ½·e_a)·dx`); a particle spreads its mass and its
//!    affine momentum `m·(v_a + c_a·(x_i − x_p))` there with quadratic
//!    B-spline weights ([`quadratic_weights`]), its external acceleration as
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
//! Everything runs on one thread in a fixed order (the CG's sums in f64), so
//! a step is the same bits whatever the pool. `benchmarks/large_step.py`
//! holds the prototype this module follows and its checks (docs/large-step.md).

use nalgebra::SVector;

use crate::kernel::quadratic_weights;
use crate::particles::Particle;

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
}

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

/// A particle's 3^D stencil on a grid of nodes at `(i + shift_d)·dx`: per axis the first node
/// (clamped so the stencil stays on the grid) and the weights and offsets `x_i − x_p` [m].
struct Stencil<const D: usize> {
    base: [usize; D],
    w: [[f32; 3]; D],
    off: [[f32; 3]; D],
}

impl<const D: usize> Stencil<D> {
    fn new(x: &SVector<f32, D>, dx: f32, axis: Option<usize>, s: &[usize; D]) -> Self {
        let mut st = Stencil {
            base: [0; D],
            w: [[0.0; 3]; D],
            off: [[0.0; 3]; D],
        };
        for d in 0..D {
            let shift = if Some(d) == axis { 0.0 } else { 0.5 };
            let g = x[d] / dx - shift;
            let b = (g - 0.5).floor();
            st.w[d] = quadratic_weights(g - b);
            let b = (b.max(0.0) as usize).min(s[d] - 3);
            st.base[d] = b;
            for k in 0..3 {
                st.off[d][k] = ((b + k) as f32 + shift) * dx - x[d];
            }
        }
        st
    }

    /// Calls `f(flat index, weight, offset)` for each of the 3^D nodes, in a fixed order (the last axis
    /// fastest), stepping an odometer over the axes rather than dividing a node number.
    #[inline(always)]
    fn each(&self, stride: &[usize; D], mut f: impl FnMut(usize, f32, SVector<f32, D>)) {
        let idx: [[usize; 3]; D] =
            std::array::from_fn(|d| std::array::from_fn(|k| (self.base[d] + k) * stride[d]));
        let mut k = [0usize; D];
        loop {
            let mut i = 0;
            let mut w = 1.0;
            let mut off = SVector::<f32, D>::zeros();
            for d in 0..D {
                i += idx[d][k[d]];
                w *= self.w[d][k[d]];
                off[d] = self.off[d][k[d]];
            }
            f(i, w, off);
            let mut d = D;
            loop {
                if d == 0 {
                    return;
                }
                d -= 1;
                k[d] += 1;
                if k[d] < 3 {
                    break;
                }
                k[d] = 0;
            }
        }
    }
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
        self.p2g(particles, dt);
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
        self.mark_fluid(particles, rho);
        let stats = self.solve(dt, rho);
        self.subtract_gradient(dt, rho);
        self.walls();
        self.g2p(particles, dt);
        stats
    }

    fn p2g(&mut self, particles: &[Particle<D>], dt: f32) {
        let (n, dx) = (self.n, self.dx);
        for a in 0..D {
            let s = shape::<D>(n, Some(a));
            let stride = strides(&s);
            let (vel, mass) = (&mut self.vel[a], &mut self.mass[a]);
            vel.iter_mut().for_each(|v| *v = 0.0);
            mass.iter_mut().for_each(|m| *m = 0.0);
            for p in particles {
                let va = p.v[a] + dt * p.ext[a];
                let ca = p.c.row(a).transpose();
                Stencil::new(&p.x, dx, Some(a), &s).each(&stride, |i, w, off| {
                    mass[i] += p.mass * w;
                    vel[i] += p.mass * w * (va + ca.dot(&off));
                });
            }
            for (v, m) in vel.iter_mut().zip(mass.iter()) {
                *v = if *m > 0.0 { *v / *m } else { 0.0 };
            }
        }
    }

    /// Free slip: zero the normal faces in and on the walls; inside a wall the tangential components copy the fluid's.
    fn walls(&mut self) {
        let (n, ws) = (self.n, self.ws);
        for a in 0..D {
            let s = shape::<D>(n, Some(a));
            let stride = strides(&s);
            let vel = &mut self.vel[a];
            let total = vel.len();
            for flat in 0..total {
                let mut r = flat;
                let mut idx = [0usize; D];
                for d in 0..D {
                    idx[d] = r / stride[d];
                    r %= stride[d];
                }
                if idx[a] <= ws || idx[a] >= n - ws {
                    vel[flat] = 0.0;
                    continue;
                }
                // the nearest face inside the fluid region along each tangential axis
                let mut src = flat;
                for b in 0..D {
                    if b == a {
                        continue;
                    }
                    let i = idx[b];
                    let j = i.clamp(ws, n - ws - 1);
                    src = src - i * stride[b] + j * stride[b];
                }
                if src != flat {
                    vel[flat] = vel[src];
                }
            }
        }
    }

    fn is_solid(&self, idx: &[usize; D]) -> bool {
        idx.iter().any(|&i| i < self.ws || i >= self.n - self.ws)
    }

    fn mark_fluid(&mut self, particles: &[Particle<D>], rho: f32) {
        let (n, dx) = (self.n, self.dx);
        let s = shape::<D>(n, None);
        let stride = strides(&s);
        self.density.iter_mut().for_each(|d| *d = 0.0);
        self.index.iter_mut().for_each(|i| *i = u32::MAX);
        let scale = 1.0 / (dx.powi(D as i32) * rho);
        let density = &mut self.density;
        for p in particles {
            Stencil::new(&p.x, dx, None, &s)
                .each(&stride, |i, w, _| density[i] += p.mass * w * scale);
        }
        let mut marked = vec![false; self.index.len()];
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
        let mut x: Vec<f64> = self.fluid.iter().map(|&c| self.pressure[c]).collect();
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

    /// `u ← u − (dt/ρ)·∇p` on every face beside a fluid cell (the ghost pressure on a face to the air).
    fn subtract_gradient(&mut self, dt: f32, rho: f32) {
        let (n, dx) = (self.n, self.dx);
        let stride_c = strides(&shape::<D>(n, None));
        let k = dt / (rho * dx);
        for a in 0..D {
            let st = strides(&shape::<D>(n, Some(a)));
            for ci in 0..self.index.len() {
                // the face on the low side of cell `ci` along a, between cells ci − e_a and ci
                let idx = self.unflat(ci);
                if idx[a] == 0 {
                    continue;
                }
                let lo_c = ci - stride_c[a];
                let (fl, fr) = (self.index[lo_c] != u32::MAX, self.index[ci] != u32::MAX);
                if !fl && !fr {
                    continue;
                }
                let mut lo_idx = idx;
                lo_idx[a] -= 1;
                let (sl, sr) = (self.is_solid(&lo_idx), self.is_solid(&idx));
                let face: usize = (0..D).map(|d| idx[d] * st[d]).sum();
                let (pl, pr) = (self.pressure[lo_c] as f32, self.pressure[ci] as f32);
                let grad_dx = if fl && fr {
                    pr - pl
                } else if fl && !sr {
                    -pl / self.theta(lo_c, ci)
                } else if fr && !sl {
                    pr / self.theta(ci, lo_c)
                } else {
                    continue; // beside a wall: the wall condition sets it
                };
                self.vel[a][face] -= k * grad_dx;
            }
        }
    }

    fn g2p(&mut self, particles: &mut [Particle<D>], dt: f32) {
        let (n, dx) = (self.n, self.dx);
        let apic = 4.0 / (dx * dx);
        let strides_a: Vec<([usize; D], [usize; D])> = (0..D)
            .map(|a| {
                let s = shape::<D>(n, Some(a));
                (s, strides(&s))
            })
            .collect();
        let lo = (self.ws as f32 + 1e-3) * dx;
        let hi = 1.0 - lo;
        for p in particles.iter_mut() {
            for a in 0..D {
                let (s, stride) = &strides_a[a];
                let vel = &self.vel[a];
                let mut va = 0.0f32;
                let mut ca = SVector::<f32, D>::zeros();
                Stencil::new(&p.x, dx, Some(a), s).each(stride, |i, w, off| {
                    va += w * vel[i];
                    ca += off * (w * vel[i]);
                });
                p.v[a] = va;
                for d in 0..D {
                    p.c[(a, d)] = apic * ca[d];
                }
            }
            for d in 0..D {
                p.x[d] = (p.x[d] + dt * p.v[d]).clamp(lo, hi);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::particles::{Material, lattice_box};

    const RHO: f32 = 1000.0;

    /// Water filling the box between its walls to `depth` [m] above the floor face, 2 particles per cell per axis.
    fn tank<const D: usize>(n: usize, wall_cells: usize, depth: f32) -> Vec<Particle<D>> {
        let dx = 1.0 / n as f32;
        let face = (wall_cells - 1) as f32 * dx;
        let sp = dx / 2.0;
        let counts: [usize; D] = std::array::from_fn(|d| {
            let extent = if d == 1 { depth } else { 1.0 - 2.0 * face };
            (extent / sp).round() as usize
        });
        lattice_box([face; D], counts, sp, Material::Water, RHO)
    }

    fn gravity<const D: usize>() -> SVector<f32, D> {
        let mut g = SVector::zeros();
        g[1] = -9.8;
        g
    }

    #[test]
    fn a_column_at_rest_keeps_its_volume_and_the_hydrostatic_pressure() {
        let (n, wc, depth) = (64, 3, 0.4);
        let mut ps = tank::<2>(n, wc, depth);
        let mut pr = Projection::<2>::new(n, wc);
        let g = gravity::<2>();
        let mut last = ProjectionStats::default();
        for _ in 0..400 {
            let k = pr.steps_for(&ps, &g, 2.5e-3);
            for _ in 0..k {
                last = pr.step(&mut ps, 2.5e-3 / k as f32, &g, RHO);
            }
        }
        assert!(last.residual <= CG_TOLERANCE, "{last:?}");
        let vmax = ps.iter().map(|p| p.v.amax()).fold(0.0f32, f32::max);
        assert!(vmax < 0.01, "still moving at {vmax} m/s");
        // the pressure of the bottom fluid row (cell centres half a cell above the floor face) against ρ·g·depth
        let ws = wc - 1;
        let dx = 1.0 / n as f32;
        let row: Vec<f64> = (ws + 8..n - ws - 8)
            .map(|i| pr.pressure()[i * n + ws])
            .collect();
        let mean = row.iter().sum::<f64>() / row.len() as f64;
        let top = ps.iter().map(|p| p.x[1]).fold(0.0f32, f32::max) + dx / 4.0;
        let expected = RHO as f64 * 9.8 * (top - (ws as f32 + 0.5) * dx) as f64;
        assert!(
            (mean / expected - 1.0).abs() < 0.02,
            "pressure {mean} Pa against {expected} Pa"
        );
        let face = ws as f32 * dx;
        assert!(
            ((top - face) / depth - 1.0).abs() < 0.01,
            "surface at {} m above the floor, {depth} m at rest",
            top - face
        );
    }

    #[test]
    fn the_projection_leaves_no_divergence_on_the_fluid_cells() {
        let (n, wc) = (32, 3);
        let mut ps = tank::<3>(n, wc, 0.3);
        for p in ps.iter_mut() {
            p.v[0] = (7.0 * p.x[1]).sin();
            p.v[2] = (5.0 * p.x[0]).cos();
        }
        let mut pr = Projection::<3>::new(n, wc);
        let stats = pr.step(&mut ps, 2.5e-3, &gravity::<3>(), RHO);
        assert!(
            stats.residual <= CG_TOLERANCE && stats.fluid_cells > 1000,
            "{stats:?}"
        );
        // interior fluid cells (no air neighbour): the discrete divergence is the volume correction's alone, ~0
        let dx = 1.0 / n as f32;
        let mut worst = 0.0f32;
        for &c in &pr.fluid {
            if pr.neighbours(c)[..6]
                .iter()
                .any(|&nb| nb != usize::MAX && pr.index[nb] == u32::MAX)
                || pr.density[c] > 1.0
            {
                continue;
            }
            let idx = pr.unflat(c);
            let mut div = 0.0;
            for a in 0..3 {
                let st = strides(&shape::<3>(n, Some(a)));
                let lo: usize = (0..3).map(|d| idx[d] * st[d]).sum();
                div += pr.vel[a][lo + st[a]] - pr.vel[a][lo];
            }
            worst = worst.max((div / dx).abs());
        }
        assert!(worst < 1e-2, "divergence {worst} 1/s");
    }

    #[test]
    fn a_step_is_the_same_bits_each_time() {
        let run = || {
            let mut ps = tank::<2>(48, 3, 0.3);
            for p in ps.iter_mut().filter(|p| p.x[0] > 0.5) {
                p.v[0] = -1.0;
            }
            let mut pr = Projection::<2>::new(48, 3);
            for _ in 0..20 {
                pr.step(&mut ps, 2.5e-3, &gravity::<2>(), RHO);
            }
            ps.iter()
                .flat_map(|p| [p.x[0].to_bits(), p.x[1].to_bits(), p.v[0].to_bits()])
                .collect::<Vec<u32>>()
        };
        assert_eq!(run(), run());
    }
}
