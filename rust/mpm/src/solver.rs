//! The MLS-MPM solver (Hu et al. 2018, APIC transfers, quadratic B-splines).
//!
//! One substep = `p2g` (per sparse block, into a private padded buffer: no
//! atomics, no shared writes) → `grid_update` (per output block: gathers the
//! overlapping padded buffers in a fixed order, adds gravity, applies walls and
//! colliders) → `g2p` (per particle: new `v`, `C`, position, `J` or `F` with
//! the Drucker–Prager return map, stress, and the particle's block key for
//! the next substep).
//!
//! Grid work touches only blocks that contain particles and their `+1`
//! neighbours (the B-spline stencil reaches 2 nodes ahead), so the cost follows
//! the particle count, not the domain volume. Every reduction happens in a
//! fixed order that does not depend on the thread count: results are bitwise
//! identical for any number of threads.

use nalgebra::{SMatrix, SVector};
use rayon::prelude::*;

use crate::collider::{apply_condition, Collider};
use crate::dim::{Dim, DimOps};
use crate::error::{MpmError, Result};
use crate::params::{BoundaryCondition, SolverParams};
use crate::particles::{Material, Particle};

const EMPTY: u32 = u32::MAX;

/// Statistics of one `step_frame` call.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameStats {
    /// Substeps taken.
    pub substeps: usize,
    /// Substep size [s].
    pub dt: f32,
    /// Largest particle speed at the end of the frame [m/s].
    pub max_speed: f32,
    /// Sparse blocks holding particles during the last substep.
    pub active_blocks: usize,
    /// Times the frame was restarted with the substep halved (after a
    /// non-finite state or a CFL violation).
    pub retries: usize,
}

/// Scratch space of the sparse block grid, reused across substeps.
struct SparseGrid {
    /// (the cell cache is kept for up to 3 dimensions)
    log2_b: u32,
    /// Blocks per dimension of the block lattice.
    nb: usize,
    /// Block lattice map: block coordinate → index in `src_blocks` (or EMPTY).
    src_map: Vec<u32>,
    /// Block lattice map: block coordinate → index in `out_blocks` (or EMPTY).
    out_map: Vec<u32>,
    src_blocks: Vec<u32>,
    src_offsets: Vec<u32>,
    sorted: Vec<u32>,
    out_blocks: Vec<u32>,
    /// Padded p2g buffers, one per source block: (B+2)^D nodes of [mass, momentum (D), pad].
    local: Vec<[f32; 4]>,
    /// Grid velocities per output block: B^D nodes (padded to 4 lanes).
    out_v: Vec<[f32; 4]>,
    /// Stencil base cell, fraction and block key of each particle (storage order).
    keys: Vec<Cell>,
    next_keys: Vec<Cell>,
    counts: Vec<u32>,
}

/// Precomputed stencil offsets.
struct Stencil<const D: usize> {
    /// Strides of the padded buffer (in nodes), per dimension.
    pad_stride: [usize; D],
    /// Strides inside an output block (in nodes), per dimension.
    blk_stride: [usize; D],
    /// Strides of the block lattice, per dimension.
    lat_stride: [usize; D],
    /// Coordinates of each node of a padded (B+2)^D buffer.
    pad_coords: Vec<[usize; D]>,
}

/// MLS-MPM solver for `D` = 2 or 3.
pub struct Solver<const D: usize>
where
    Dim<D>: DimOps<D>,
{
    params: SolverParams<D>,
    colliders: Vec<Collider<D>>,
    /// Particles in storage order: sorted by sparse block, then by id.
    particles: Vec<Particle<D>>,
    /// `ids[slot]`: the public index of the particle stored at `slot`.
    ids: Vec<u32>,
    /// `slot_of[id]`: where particle `id` is stored.
    slot_of: Vec<u32>,
    /// Scratch for the next substep's storage (g2p writes here in block order).
    next: Vec<Particle<D>>,
    time: f64,
    frame: u64,
    grid: SparseGrid,
    stencil: Stencil<D>,
    pool: std::sync::Arc<rayon::ThreadPool>,
    pool_pid: u32,
    /// Print per-stage substep timings to stderr (env `HMPM_PROFILE` set at construction).
    profile: bool,
}

fn build_pool(num_threads: usize) -> Result<std::sync::Arc<rayon::ThreadPool>> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(num_threads)
        .build()
        .map(std::sync::Arc::new)
        .map_err(|e| MpmError::invalid("num_threads", format!("cannot start the thread pool: {e}")))
}

/// Where a particle sits in the grid: the base node of its 3^D stencil,
/// its offset from it (in cells, in [0.5, 1.5)) and its block's key.
/// Computed once per substep (in g2p, for the next one).
#[derive(Clone, Copy, Debug, Default)]
struct Cell {
    key: u32,
    base: [u32; 3],
    fx: [f32; 3],
}

#[inline(always)]
fn cell_of<const D: usize>(x: &SVector<f32, D>, inv_dx: f32, log2_b: u32, lat: &[usize; D]) -> Cell {
    let mut c = Cell::default();
    let mut key = 0usize;
    for d in 0..D {
        let xg = x[d] * inv_dx;
        // xg ≥ 1 inside the domain [dx, 1 − dx], so truncation is floor
        let b = (xg - 0.5) as u32;
        c.base[d] = b;
        c.fx[d] = xg - b as f32;
        key += (b as usize >> log2_b) * lat[d];
    }
    c.key = key as u32;
    c
}

/// Quadratic B-spline weights (Hu et al. 2018, Eq. 4 ff.) for offsets `fx`.
#[inline(always)]
fn weights<const D: usize>(cell: &Cell) -> (SVector<f32, D>, [[f32; 3]; D]) {
    let mut fx = SVector::<f32, D>::zeros();
    let mut w = [[0.0f32; 3]; D];
    for d in 0..D {
        let f = cell.fx[d];
        fx[d] = f;
        w[d] = [0.5 * (1.5 - f) * (1.5 - f), 0.75 - (f - 1.0) * (f - 1.0), 0.5 * (f - 0.5) * (f - 0.5)];
    }
    (fx, w)
}

impl<const D: usize> Solver<D>
where
    Dim<D>: DimOps<D>,
{
    /// A solver with no particles. Errors name the bad parameter.
    pub fn new(params: SolverParams<D>, colliders: Vec<Collider<D>>) -> Result<Self> {
        assert!(D == 2 || D == 3);
        params.validate()?;
        for (i, c) in colliders.iter().enumerate() {
            c.validate(&format!("colliders[{i}]"))?;
        }
        let log2_b = <Dim<D> as DimOps<D>>::LOG2_BLOCK;
        let b = 1usize << log2_b;
        // nodes 0..=n+1 may be touched; +1 block for the stencil's reach.
        let nb = (params.n_grid + 2).div_ceil(b) + 1;
        let lattice = nb.pow(D as u32);
        let p = b + 2;
        let mut pad_stride = [0usize; D];
        let mut blk_stride = [0usize; D];
        let mut lat_stride = [0usize; D];
        for d in 0..D {
            pad_stride[d] = p.pow((D - 1 - d) as u32);
            blk_stride[d] = b.pow((D - 1 - d) as u32);
            lat_stride[d] = nb.pow((D - 1 - d) as u32);
        }
        let pad_nodes = p.pow(D as u32);
        let pad_coords = (0..pad_nodes)
            .map(|q| {
                let mut rem = q;
                let mut c = [0usize; D];
                for d in (0..D).rev() {
                    c[d] = rem % p;
                    rem /= p;
                }
                c
            })
            .collect();
        let pool = build_pool(params.num_threads)?;
        Ok(Solver {
            params,
            colliders,
            particles: Vec::new(),
            ids: Vec::new(),
            slot_of: Vec::new(),
            next: Vec::new(),
            time: 0.0,
            frame: 0,
            grid: SparseGrid {
                log2_b,
                nb,
                src_map: vec![EMPTY; lattice],
                out_map: vec![EMPTY; lattice],
                src_blocks: Vec::new(),
                src_offsets: Vec::new(),
                sorted: Vec::new(),
                out_blocks: Vec::new(),
                local: Vec::new(),
                out_v: Vec::new(),
                keys: Vec::new(),
                next_keys: Vec::new(),
                counts: Vec::new(),
            },
            stencil: Stencil { pad_stride, blk_stride, lat_stride, pad_coords },
            pool,
            pool_pid: std::process::id(),
            profile: std::env::var_os("HMPM_PROFILE").is_some(),
        })
    }

    pub fn params(&self) -> &SolverParams<D> {
        &self.params
    }

    pub fn colliders(&self) -> &[Collider<D>] {
        &self.colliders
    }

    /// The particles in their public order (index = the order they were given in).
    pub fn particles(&self) -> Vec<Particle<D>> {
        self.slot_of.iter().map(|&s| self.particles[s as usize]).collect()
    }

    /// Visit the particles in their public order.
    pub fn for_each_particle(&self, mut f: impl FnMut(usize, &Particle<D>)) {
        for (i, &s) in self.slot_of.iter().enumerate() {
            f(i, &self.particles[s as usize]);
        }
    }

    fn reset_order(&mut self) {
        let n = self.particles.len() as u32;
        self.ids = (0..n).collect();
        self.slot_of = (0..n).collect();
    }

    pub fn num_particles(&self) -> usize {
        self.particles.len()
    }

    /// Simulated time [s].
    pub fn time(&self) -> f64 {
        self.time
    }

    /// Frames advanced so far.
    pub fn frame(&self) -> u64 {
        self.frame
    }

    /// Lower and upper bound of valid particle coordinates: one cell inside the domain.
    pub fn domain_bounds(&self) -> (f32, f32) {
        let dx = self.params.dx();
        (dx, 1.0 - dx)
    }

    /// Replace all particles (validated; derived stress recomputed).
    pub fn set_particles(&mut self, mut particles: Vec<Particle<D>>) -> Result<()> {
        let (lo, hi) = self.domain_bounds();
        for (i, p) in particles.iter().enumerate() {
            p.validate(i, lo, hi)?;
        }
        for p in particles.iter_mut() {
            self.refresh_stress(p);
        }
        self.particles = particles;
        self.reset_order();
        Ok(())
    }

    /// Replace all particles keeping their stored stress (checkpoint restore).
    pub(crate) fn set_particles_keep_stress(&mut self, particles: Vec<Particle<D>>) -> Result<()> {
        let (lo, hi) = self.domain_bounds();
        for (i, p) in particles.iter().enumerate() {
            p.validate(i, lo, hi)?;
            if !p.tau.iter().all(|a| a.is_finite()) {
                return Err(MpmError::invalid("stress", format!("particle {i} has a non-finite stress")));
            }
        }
        self.particles = particles;
        self.reset_order();
        Ok(())
    }

    /// Modify particles in place through `f(id, particle)` (public order),
    /// then validate; `refresh_stress` recomputes τ (needed after changing
    /// `F`, `J` or `C`). On error nothing changes.
    pub fn modify_particles(&mut self, refresh_stress: bool, mut f: impl FnMut(usize, &mut Particle<D>)) -> Result<()> {
        let mut ps = self.particles.clone();
        for (id, &slot) in self.slot_of.iter().enumerate() {
            f(id, &mut ps[slot as usize]);
        }
        let (lo, hi) = self.domain_bounds();
        for (id, &slot) in self.slot_of.iter().enumerate() {
            ps[slot as usize].validate(id, lo, hi)?;
        }
        if refresh_stress {
            for p in ps.iter_mut() {
                self.refresh_stress(p);
            }
        }
        self.particles = ps;
        Ok(())
    }

    /// Append particles (validated). Returns the new particle count.
    pub fn add_particles(&mut self, new: Vec<Particle<D>>) -> Result<usize> {
        let (lo, hi) = self.domain_bounds();
        let n0 = self.particles.len();
        for (i, p) in new.iter().enumerate() {
            p.validate(n0 + i, lo, hi)?;
        }
        for mut p in new {
            self.refresh_stress(&mut p);
            self.ids.push(self.particles.len() as u32);
            self.slot_of.push(self.particles.len() as u32);
            self.particles.push(p);
        }
        Ok(self.particles.len())
    }

    /// Remove the particles whose `keep[i]` is false (order of the rest kept).
    pub fn retain_particles(&mut self, keep: &[bool]) -> Result<usize> {
        if keep.len() != self.particles.len() {
            return Err(MpmError::invalid("mask", format!("length {} != particle count {}", keep.len(), self.particles.len())));
        }
        let kept: Vec<Particle<D>> =
            self.particles().into_iter().zip(keep.iter()).filter(|(_, k)| **k).map(|(p, _)| p).collect();
        self.particles = kept;
        self.reset_order();
        Ok(self.particles.len())
    }

    /// Set simulated time and frame counter (used by checkpoint restore).
    pub fn set_clock(&mut self, time: f64, frame: u64) {
        self.time = time;
        self.frame = frame;
    }

    fn refresh_stress(&self, p: &mut Particle<D>) {
        p.tau = match p.material {
            Material::Water => self.water_stress(p.j, &p.c),
            Material::Sand => {
                let svd = Dim::<D>::svd(&p.f);
                let eps = svd.sigma.map(|s| s.max(1e-6).ln());
                self.sand_stress(&svd.u, &eps)
            }
        };
    }

    #[inline(always)]
    fn water_stress(&self, j: f32, c: &SMatrix<f32, D, D>) -> SMatrix<f32, D, D> {
        let w = &self.params.water;
        let mut tau = SMatrix::<f32, D, D>::identity() * (w.bulk_modulus * j * (j - 1.0));
        if w.viscosity > 0.0 {
            tau += (c + c.transpose()) * (w.viscosity * j);
        }
        tau
    }

    #[inline(always)]
    fn sand_stress(&self, u: &SMatrix<f32, D, D>, eps: &SVector<f32, D>) -> SMatrix<f32, D, D> {
        let (mu, la) = self.params.sand.lame();
        let tr = eps.sum();
        let diag = eps.map(|e| 2.0 * mu * e + la * tr);
        u * SMatrix::<f32, D, D>::from_diagonal(&diag) * u.transpose()
    }

    /// Largest wave speed among the materials present [m/s].
    fn wave_speed(&self) -> f32 {
        let mut has = [false; 2];
        for p in &self.particles {
            has[p.material as usize] = true;
            if has[0] && has[1] {
                break;
            }
        }
        let mut c = 0.0f32;
        if has[0] {
            c = c.max(self.params.water.wave_speed());
        }
        if has[1] {
            c = c.max(self.params.sand.wave_speed());
        }
        c
    }

    /// Substep count the CFL condition asks for over a frame of `dt_frame` seconds.
    pub fn substeps_for(&self, dt_frame: f32) -> usize {
        if let Some(s) = self.params.substeps {
            return s;
        }
        let vmax = self.pool.install(|| {
            self.particles.par_iter().map(|p| p.v.norm()).reduce(|| 0.0f32, f32::max)
        });
        let dt_max = self.params.cfl * self.params.dx() / (self.wave_speed() + vmax).max(1e-6);
        ((dt_frame / dt_max).ceil() as usize).max(1)
    }

    /// Advance one frame of `dt_frame` seconds (default 2.5e-3) in as many
    /// substeps as the CFL condition requires (`cfl·dx / (c + |v|max)`), or
    /// `params.substeps` if set.
    ///
    /// Stability: when a substep leaves a non-finite state or violates the
    /// CFL condition (a particle would travel more than one cell `dx` in a
    /// substep), the frame is rolled back to its start and retried with the
    /// substep halved, up to `max_substeps` (`FrameStats::retries` counts the
    /// restarts).
    ///
    /// Errors: `InvalidInput` for a bad `dt_frame` or when more than
    /// `max_substeps` would be needed; `NonFinite` / `CflViolation` when even
    /// `max_substeps` substeps fail, in which case the state is restored to
    /// the start of the frame.
    pub fn step_frame(&mut self, dt_frame: f32) -> Result<FrameStats> {
        if !(dt_frame.is_finite() && dt_frame > 0.0 && dt_frame <= 1.0) {
            return Err(MpmError::invalid("dt_frame", format!("must be in (0, 1] s, got {dt_frame}")));
        }
        if self.pool_pid != std::process::id() {
            // We are in a forked child: the parent's worker threads do not exist here.
            self.pool = build_pool(self.params.num_threads)?;
            self.pool_pid = std::process::id();
        }
        let n_sub = self.substeps_for(dt_frame);
        if n_sub > self.params.max_substeps {
            return Err(MpmError::invalid(
                "dt_frame",
                format!(
                    "the CFL condition needs {n_sub} substeps for dt_frame = {dt_frame} s, more than max_substeps = {}",
                    self.params.max_substeps
                ),
            ));
        }
        if self.particles.is_empty() {
            self.time += dt_frame as f64;
            self.frame += 1;
            let dt = dt_frame / n_sub as f32;
            return Ok(FrameStats { substeps: n_sub, dt, max_speed: 0.0, active_blocks: 0, retries: 0 });
        }
        let backup = (self.particles.clone(), self.ids.clone(), self.slot_of.clone());
        let pool = self.pool.clone();
        let max_travel = self.params.dx(); // a particle may not cross more than one cell per substep
        let mut n_sub = n_sub;
        let mut retries = 0;
        loop {
            let dt = dt_frame / n_sub as f32;
            let result = pool.install(|| {
                self.compute_keys();
                let mut vmax = 0.0;
                for s in 0..n_sub {
                    let (finite, v) = self.substep(dt);
                    vmax = v;
                    if !finite {
                        return Err(MpmError::NonFinite { substep: s, substeps: n_sub, retries });
                    }
                    if v * dt > max_travel {
                        return Err(MpmError::CflViolation { substep: s, substeps: n_sub, max_speed: v, retries });
                    }
                }
                Ok(vmax)
            });
            match result {
                Ok(vmax) => {
                    self.time += dt_frame as f64;
                    self.frame += 1;
                    let active_blocks = self.grid.src_blocks.len();
                    return Ok(FrameStats { substeps: n_sub, dt, max_speed: vmax, active_blocks, retries });
                }
                Err(e) => {
                    // Roll back to the frame's start; retry with the substep halved
                    // while the substep budget allows it.
                    (self.particles, self.ids, self.slot_of) = backup.clone();
                    if 2 * n_sub > self.params.max_substeps {
                        return Err(e);
                    }
                    n_sub *= 2;
                    retries += 1;
                }
            }
        }
    }

    /// Block key of every particle (from its stencil base node).
    fn compute_keys(&mut self) {
        let inv_dx = self.params.n_grid as f32;
        let log2_b = self.grid.log2_b;
        let lat = self.stencil.lat_stride;
        self.grid.keys.resize(self.particles.len(), Cell::default());
        self.particles.par_iter().zip(self.grid.keys.par_iter_mut()).for_each(|(p, k)| {
            *k = cell_of::<D>(&p.x, inv_dx, log2_b, &lat);
        });
    }

    /// Sort particles into blocks (stable counting sort) and list output blocks.
    fn build_blocks(&mut self) {
        let g = &mut self.grid;
        for &b in &g.src_blocks {
            g.src_map[b as usize] = EMPTY;
        }
        for &b in &g.out_blocks {
            g.out_map[b as usize] = EMPTY;
        }
        g.src_blocks.clear();
        g.out_blocks.clear();
        g.counts.clear();
        // Visit particles in id order so that the order inside each block (and
        // so every floating-point sum) depends only on the particle set.
        for &slot_id in &self.slot_of {
            let k = g.keys[slot_id as usize].key;
            let slot = &mut g.src_map[k as usize];
            if *slot == EMPTY {
                *slot = g.src_blocks.len() as u32;
                g.src_blocks.push(k);
                g.counts.push(0);
            }
            g.counts[*slot as usize] += 1;
        }
        g.src_offsets.clear();
        g.src_offsets.push(0);
        let mut acc = 0u32;
        for &c in &g.counts {
            acc += c;
            g.src_offsets.push(acc);
        }
        // reuse counts as cursors
        for (c, &o) in g.counts.iter_mut().zip(g.src_offsets.iter()) {
            *c = o;
        }
        g.sorted.resize(g.keys.len(), 0);
        for &slot_id in &self.slot_of {
            let k = g.keys[slot_id as usize].key;
            let s = g.src_map[k as usize] as usize;
            g.sorted[g.counts[s] as usize] = slot_id;
            g.counts[s] += 1;
        }
        // Output blocks: each source block and its +1 neighbours.
        let lat = self.stencil.lat_stride;
        let nb = g.nb;
        for &b in &g.src_blocks {
            let c = unflatten::<D>(b as usize, &lat);
            for s in 0..(1usize << D) {
                let mut lin = 0usize;
                let mut ok = true;
                for d in 0..D {
                    let cd = c[d] + ((s >> d) & 1);
                    if cd >= nb {
                        ok = false;
                    }
                    lin += cd * lat[d];
                }
                if ok && g.out_map[lin] == EMPTY {
                    g.out_map[lin] = g.out_blocks.len() as u32;
                    g.out_blocks.push(lin as u32);
                }
            }
        }
    }

    /// One substep of size `dt`. Returns (state finite, max speed).
    fn substep(&mut self, dt: f32) -> (bool, f32) {
        let prof = self.profile;
        let t0 = std::time::Instant::now();
        self.build_blocks();
        let t1 = std::time::Instant::now();
        self.p2g(dt);
        let t2 = std::time::Instant::now();
        self.grid_update(dt);
        let t3 = std::time::Instant::now();
        let r = self.g2p(dt);
        let t4 = std::time::Instant::now();
        if prof {
            eprintln!("blocks {:?} p2g {:?} grid {:?} g2p {:?} nsrc {} nout {}", t1 - t0, t2 - t1, t3 - t2, t4 - t3, self.grid.src_blocks.len(), self.grid.out_blocks.len());
        }
        r
    }

    fn p2g(&mut self, dt: f32) {
        let b = 1usize << self.grid.log2_b;
        let pad_nodes = (b + 2).pow(D as u32);
        let n_src = self.grid.src_blocks.len();
        let dx = self.params.dx();
        let inv_dx = 1.0 / dx;
        let stress_scale = -dt * 4.0 * inv_dx * inv_dx;
        let g = &mut self.grid;
        g.local.resize(n_src * pad_nodes, [0.0; 4]);
        let particles = &self.particles;
        let st = &self.stencil;
        let (src_blocks, src_offsets, sorted, lat, log2_b, cells) =
            (&g.src_blocks, &g.src_offsets, &g.sorted, st.lat_stride, g.log2_b, &g.keys);
        g.local.par_chunks_mut(pad_nodes).enumerate().for_each(|(si, buf)| {
            buf.fill([0.0; 4]);
            let c = unflatten::<D>(src_blocks[si] as usize, &lat);
            let lo = src_offsets[si] as usize;
            let hi = src_offsets[si + 1] as usize;
            for &pi in &sorted[lo..hi] {
                let p = &particles[pi as usize];
                let cell = &cells[pi as usize];
                let (fx, w) = weights::<D>(cell);
                let mut base_idx = 0usize;
                for d in 0..D {
                    base_idx += (cell.base[d] as usize - (c[d] << log2_b)) * st.pad_stride[d];
                }
                // [mass, momentum + affine·dpos] with dpos = (o − fx)·dx, written
                // as base + Σ_c o_c·col_c (o integer offsets): 4-wide vector work
                let a_mat = (p.tau * (stress_scale * p.volume) + p.c * p.mass) * dx;
                let mom = (p.v + p.ext * dt) * p.mass;
                let q = mom - a_mat * fx;
                let mut base4 = [p.mass, 0.0, 0.0, 0.0];
                let mut cols = [[0.0f32; 4]; D];
                for r in 0..D {
                    base4[1 + r] = q[r];
                    for c in 0..D {
                        cols[c][1 + r] = a_mat[(r, c)];
                    }
                }
                let nodes = &mut buf[base_idx..];
                let w_last = w[D - 1];
                let last = cols[D - 1];
                Dim::<D>::stencil_rows(&w, &st.pad_stride, |off, w_outer, o| {
                    let mut contrib = base4;
                    for c in 0..D - 1 {
                        fma4(&mut contrib, o[c], &cols[c]);
                    }
                    // the row's 3 nodes are contiguous (last stride 1)
                    let row = &mut nodes[off..off + 3];
                    for k in 0..3 {
                        fma4(&mut row[k], w_outer * w_last[k], &contrib);
                        add4(&mut contrib, &last);
                    }
                });
            }
        });
    }

    fn grid_update(&mut self, dt: f32) {
        let b = 1usize << self.grid.log2_b;
        let blk_nodes = b.pow(D as u32);
        let p = b + 2;
        let pad_nodes = p.pow(D as u32);
        let n_out = self.grid.out_blocks.len();
        let n = self.params.n_grid;
        let dx = self.params.dx();
        let gravity = SVector::<f32, D>::from_column_slice(&self.params.gravity);
        let walls = self.params.walls.clone();
        let colliders = &self.colliders;
        let st = &self.stencil;
        let g = &mut self.grid;
        g.out_v.resize(n_out * blk_nodes, [0.0; 4]);
        let (out_blocks, src_map, local, lat, log2_b) = (&g.out_blocks, &g.src_map, &g.local, st.lat_stride, g.log2_b);
        let wall_lo = walls.cells;
        let wall_hi = n.saturating_sub(walls.cells);
        g.out_v.par_chunks_mut(blk_nodes).enumerate().for_each_init(|| vec![[0.0f32; 4]; blk_nodes], |acc, (oi, out)| {
            let c = unflatten::<D>(out_blocks[oi] as usize, &lat);
            acc.fill([0.0; 4]);
            // Gather from source blocks c - s, s ∈ {0,1}^D, in a fixed order.
            for s in 0..(1usize << D) {
                let mut lin = 0usize;
                let mut ok = true;
                for d in 0..D {
                    let sd = (s >> d) & 1;
                    if c[d] < sd {
                        ok = false;
                        break;
                    }
                    lin += (c[d] - sd) * lat[d];
                }
                if !ok {
                    continue;
                }
                let sid = src_map[lin];
                if sid == EMPTY {
                    continue;
                }
                let src = &local[sid as usize * pad_nodes..(sid as usize + 1) * pad_nodes];
                for l in 0..blk_nodes {
                    let lc = unflatten_pow2::<D>(l, log2_b);
                    let mut pidx = 0usize;
                    let mut inside = true;
                    for d in 0..D {
                        let sd = (s >> d) & 1;
                        let q = sd * b + lc[d];
                        if q >= p {
                            inside = false;
                            break;
                        }
                        pidx += q * st.pad_stride[d];
                    }
                    if !inside {
                        continue;
                    }
                    let a = &mut acc[l];
                    let sv = &src[pidx];
                    for k in 0..4 {
                        a[k] += sv[k];
                    }
                }
            }
            // Block-level test: is any collider near this block?
            let near: Vec<&Collider<D>> = if colliders.is_empty() {
                Vec::new()
            } else {
                let mut centre = SVector::<f32, D>::zeros();
                for d in 0..D {
                    centre[d] = ((c[d] << log2_b) as f32 + 0.5 * (b as f32 - 1.0)) * dx;
                }
                let half_diag = 0.5 * (b as f32) * dx * (D as f32).sqrt() + dx;
                colliders.iter().filter(|col| col.shape.sdf(&centre) < half_diag).collect()
            };
            for l in 0..blk_nodes {
                let a = &acc[l];
                let m = a[0];
                let o = &mut out[l];
                if m <= 0.0 {
                    *o = [0.0; 4];
                    continue;
                }
                let mut v = SVector::<f32, D>::zeros();
                for d in 0..D {
                    v[d] = a[1 + d] / m;
                }
                v += gravity * dt;
                let lc = unflatten_pow2::<D>(l, log2_b);
                let mut gi = [0usize; D];
                for d in 0..D {
                    gi[d] = (c[d] << log2_b) + lc[d];
                }
                for col in &near {
                    let mut xp = SVector::<f32, D>::zeros();
                    for d in 0..D {
                        xp[d] = gi[d] as f32 * dx;
                    }
                    if col.shape.sdf(&xp) < 0.0 {
                        let nrm = col.shape.normal(&xp);
                        apply_condition(&mut v, &nrm, col.condition, col.friction);
                    }
                }
                for d in 0..D {
                    if gi[d] < wall_lo {
                        let mut nrm = SVector::<f32, D>::zeros();
                        nrm[d] = 1.0;
                        wall_condition(&mut v, &nrm, walls.condition, walls.friction);
                    } else if gi[d] > wall_hi {
                        let mut nrm = SVector::<f32, D>::zeros();
                        nrm[d] = -1.0;
                        wall_condition(&mut v, &nrm, walls.condition, walls.friction);
                    }
                }
                o[..D].copy_from_slice(v.as_slice());
            }
        });
    }

    /// g2p in block order: each source block gathers its padded velocity
    /// patch once, its particles read it with fixed strides and are written
    /// contiguously into the next storage (sorted by block, then id).
    fn g2p(&mut self, dt: f32) -> (bool, f32) {
        let dx = self.params.dx();
        let inv_dx = 1.0 / dx;
        let (lo, hi) = self.domain_bounds();
        let log2_b = self.grid.log2_b;
        let b = 1usize << log2_b;
        let bmask = b - 1;
        let blk_nodes = 1usize << (log2_b as usize * D);
        let st = &self.stencil;
        let lat = st.lat_stride;
        let sand = self.params.sand.clone();
        let (mu, la) = sand.lame();
        let alpha = Dim::<D>::drucker_prager_alpha(sand.friction_angle_deg.to_radians());
        let tan_phi = sand.friction_angle_deg.to_radians().tan();
        let tr_apex = if sand.cohesion > 0.0 { D as f32 * sand.cohesion / (tan_phi * (D as f32 * la + 2.0 * mu)) } else { 0.0 };
        let water = self.params.water.clone();
        let n = self.particles.len();
        let g = &mut self.grid;
        let (out_map, out_v, src_blocks, src_offsets, sorted) = (&g.out_map, &g.out_v, &g.src_blocks, &g.src_offsets, &g.sorted);
        let particles = &self.particles;
        self.next.resize(n, particles[0]);
        g.next_keys.resize(n, Cell::default());
        let cells = &g.keys;
        // split the outputs into one contiguous slice per source block
        let mut out_slices: Vec<(&mut [Particle<D>], &mut [Cell])> = Vec::with_capacity(src_blocks.len());
        let mut rest_p: &mut [Particle<D>] = &mut self.next[..];
        let mut rest_k: &mut [Cell] = &mut g.next_keys[..];
        for si in 0..src_blocks.len() {
            let len = (src_offsets[si + 1] - src_offsets[si]) as usize;
            let (ap, bp) = rest_p.split_at_mut(len);
            let (ak, bk) = rest_k.split_at_mut(len);
            out_slices.push((ap, ak));
            rest_p = bp;
            rest_k = bk;
        }
        let result = out_slices
            .into_par_iter()
            .enumerate()
            .map_init(|| vec![[0.0f32; 4]; st.pad_coords.len()], |patch, (si, (outp, outk))| {
                let c = unflatten::<D>(src_blocks[si] as usize, &lat);
                // padded velocity patch of this block: nodes c·B + q, q ∈ [0, B+2)^D
                // (every node lies in an output block, so all are overwritten)
                for (q, qc) in st.pad_coords.iter().enumerate() {
                    let mut lin = 0usize;
                    let mut off = 0usize;
                    for d in 0..D {
                        let gi = (c[d] << log2_b) + qc[d];
                        lin += (gi >> log2_b) * lat[d];
                        off += (gi & bmask) * st.blk_stride[d];
                    }
                    let ob = out_map[lin];
                    if ob != EMPTY {
                        patch[q] = out_v[ob as usize * blk_nodes + off];
                    }
                }
                let lo_i = src_offsets[si] as usize;
                let mut nan_probe = 0.0f32;
                let mut nonpositive_j = false;
                let mut vmax2 = 0.0f32;
                for (j, (po, ko)) in outp.iter_mut().zip(outk.iter_mut()).enumerate() {
                    let slot = sorted[lo_i + j] as usize;
                    let mut p = particles[slot];
                    let cell = &cells[slot];
                    let (fx, w) = weights::<D>(cell);
                    let mut base_idx = 0usize;
                    for d in 0..D {
                        base_idx += (cell.base[d] as usize - (c[d] << log2_b)) * st.pad_stride[d];
                    }
                    let mut acc_v = [0.0f32; 4];
                    let mut acc_b = [[0.0f32; 4]; D];
                    let nodes = &patch[base_idx..];
                    let w_last = w[D - 1];
                    Dim::<D>::stencil_rows(&w, &st.pad_stride, |off, w_outer, o| {
                        let row = &nodes[off..off + 3];
                        // Σ_k w_k g_k and Σ_k k·w_k g_k along the row
                        let mut sum = [0.0f32; 4];
                        let mut sum_k = [0.0f32; 4];
                        for k in 0..3 {
                            let wk = w_last[k];
                            fma4(&mut sum, wk, &row[k]);
                            fma4(&mut sum_k, wk * k as f32, &row[k]);
                        }
                        for l in 0..4 {
                            sum[l] *= w_outer;
                            sum_k[l] *= w_outer;
                        }
                        add4(&mut acc_v, &sum);
                        for c in 0..D - 1 {
                            fma4(&mut acc_b[c], o[c], &sum);
                        }
                        add4(&mut acc_b[D - 1], &sum_k);
                    });
                    // B = Σ w v (o − fx)ᵀ·dx; C = 4/dx² · B = 4/dx · (Σ w v oᵀ − v fxᵀ)
                    let new_v = SVector::<f32, D>::from_fn(|r, _| acc_v[r]);
                    let new_c = SMatrix::<f32, D, D>::from_fn(|r, c| (acc_b[c][r] - acc_v[r] * fx[c]) * (4.0 * inv_dx));
                    p.v = new_v;
                    p.c = new_c;
                    p.x += new_v * dt;
                    for d in 0..D {
                        p.x[d] = p.x[d].max(lo).min(hi);
                    }
                    match p.material {
                        Material::Water => {
                            p.j *= 1.0 + dt * new_c.trace();
                            let mut tau = SMatrix::<f32, D, D>::identity() * (water.bulk_modulus * p.j * (p.j - 1.0));
                            if water.viscosity > 0.0 {
                                tau += (new_c + new_c.transpose()) * (water.viscosity * p.j);
                            }
                            p.tau = tau;
                        }
                        Material::Sand => {
                            let f_trial = (SMatrix::<f32, D, D>::identity() + new_c * dt) * p.f;
                            let svd = Dim::<D>::svd(&f_trial);
                            let e0 = svd.sigma.map(|s| s.max(1e-6).ln());
                            let e_new = drucker_prager_project::<D>(&e0, &mut p.vc, alpha, mu, la, tr_apex);
                            if e_new == e0 {
                                // inside the cone: elastic, F is the trial F
                                p.f = f_trial;
                            } else {
                                p.f = svd.u * SMatrix::<f32, D, D>::from_diagonal(&e_new.map(f32::exp)) * svd.v.transpose();
                            }
                            let tr = e_new.sum();
                            let diag = e_new.map(|e| 2.0 * mu * e + la * tr);
                            p.tau = svd.u * SMatrix::<f32, D, D>::from_diagonal(&diag) * svd.u.transpose();
                        }
                    }
                    *ko = cell_of::<D>(&p.x, inv_dx, log2_b, &lat);
                    // NaN/inf propagate through the sum; J ≤ 0 is a blow-up too
                    nan_probe += p.v.sum() + p.tau.sum() + p.j;
                    nonpositive_j |= p.j <= 0.0;
                    vmax2 = vmax2.max(p.v.norm_squared());
                    *po = p;
                }
                // positions are clamped (NaN maps to the bound), so test velocities and stress
                (nan_probe.is_finite() && vmax2.is_finite() && !nonpositive_j, vmax2.sqrt())
            })
            .reduce(|| (true, 0.0f32), |a, b| (a.0 && b.0, a.1.max(b.1)));
        // the next storage order is the sorted order
        std::mem::swap(&mut self.particles, &mut self.next);
        std::mem::swap(&mut g.keys, &mut g.next_keys);
        let ids_old = std::mem::take(&mut self.ids);
        self.ids = sorted.iter().map(|&s| ids_old[s as usize]).collect();
        for (slot, &id) in self.ids.iter().enumerate() {
            self.slot_of[id as usize] = slot as u32;
        }
        result
    }
}

/// Domain walls: the `Sticky` wall keeps only nothing, `Slip` removes the
/// normal component, `Separate` removes the inward normal component and
/// applies Coulomb friction.
#[inline(always)]
fn wall_condition<const D: usize>(v: &mut SVector<f32, D>, n: &SVector<f32, D>, c: BoundaryCondition, friction: f32) {
    apply_condition(v, n, c, friction);
}

/// Drucker–Prager return mapping in Hencky strain (Klár et al. 2016, Sec. 7.3,
/// with the volume correction of Tampubolon et al. 2017, Eq. 26–27).
///
/// `e0`: principal log strains of the trial elastic F; `vc`: accumulated log
/// volume correction (updated); `alpha`: cone coefficient; `mu`, `la`: Lamé
/// parameters; `tr_apex`: trace of the strain at the cone apex (cohesion).
/// Returns the projected principal log strains.
pub fn drucker_prager_project<const D: usize>(
    e0: &SVector<f32, D>,
    vc: &mut f32,
    alpha: f32,
    mu: f32,
    la: f32,
    tr_apex: f32,
) -> SVector<f32, D> {
    let dd = D as f32;
    let shift = tr_apex / dd;
    let e = e0.map(|x| x + *vc / dd - shift);
    let tr = e.sum();
    let ehat = e.map(|x| x - tr / dd);
    let ehat_norm = ehat.norm();
    let e_new = if tr >= 0.0 {
        // expansion: project to the cone tip
        SVector::<f32, D>::from_element(shift)
    } else {
        let dgamma = ehat_norm + (dd * la + 2.0 * mu) / (2.0 * mu) * tr * alpha;
        if dgamma <= 0.0 {
            // inside the cone: elastic, no volume correction applied
            *e0
        } else {
            (e - ehat * (dgamma / ehat_norm)).map(|x| x + shift)
        }
    };
    *vc += e0.sum() - e_new.sum();
    e_new
}

/// `acc += s·v` on 4 lanes (compiles to one vector FMA/mul-add).
#[inline(always)]
fn fma4(acc: &mut [f32; 4], s: f32, v: &[f32; 4]) {
    for k in 0..4 {
        acc[k] += s * v[k];
    }
}

#[inline(always)]
fn add4(acc: &mut [f32; 4], v: &[f32; 4]) {
    for k in 0..4 {
        acc[k] += v[k];
    }
}

#[inline(always)]
fn unflatten<const D: usize>(mut lin: usize, strides: &[usize; D]) -> [usize; D] {
    let mut c = [0usize; D];
    for d in 0..D {
        c[d] = lin / strides[d];
        lin %= strides[d];
    }
    c
}

#[inline(always)]
fn unflatten_pow2<const D: usize>(lin: usize, log2_b: u32) -> [usize; D] {
    let mask = (1usize << log2_b) - 1;
    let mut c = [0usize; D];
    for d in 0..D {
        c[d] = (lin >> (log2_b as usize * (D - 1 - d))) & mask;
    }
    c
}
