//! The projection step's particle-grid transfers on the MAC grid: a
//! particle's quadratic B-spline weights on both grids of each axis, p2g in
//! two fixed parts of the particles, g2p one axis at a time (in 3D four
//! particles at once, one a vector lane).

use nalgebra::SVector;

use super::{Grid, shape, strides};
use crate::isa::{Isa, x86_64_v3};
use crate::kernel::quadratic_weights;
use crate::particles::Particle;
use crate::v4::V4;

/// A stencil's rows along its last axis: per row the first node's flat index, the other axes' weight
/// product and affine sum; the row count; the last axis' weights and affine terms.
type Rows = ([(usize, f32, f32); 9], usize, [f32; 3], [f32; 3]);

/// Per axis of a 3^D stencil: the nodes' parts of the flat index, weights, offsets [m]; the last axis' node count.
type Axes = ([[usize; 3]; 3], [[f32; 3]; 3], [[f32; 3]; 3], usize);

/// A particle's quadratic B-spline weights on the two grids of each axis:
/// kind 0, the cell centres `(i + ½)·dx`; kind 1, the nodes `i·dx` (a
/// velocity component's own axis on its face grid). Per axis and kind: the
/// stencil's first node (clamped so the stencil stays on the grid), the
/// weights, and the offsets `x_i − x_p` [m]; and the cell the particle is in (clamped to the grid).
pub(super) struct Kernel<const D: usize> {
    pub(super) cell: [usize; D],
    base: [[usize; 2]; D],
    w: [[[f32; 3]; 2]; D],
    off: [[[f32; 3]; 2]; D],
}

impl<const D: usize> Kernel<D> {
    #[inline(always)]
    pub(super) fn new(x: &SVector<f32, D>, dx: f32, n: usize) -> Self {
        let mut k = Kernel {
            cell: std::array::from_fn(|d| ((x[d] / dx) as usize).min(n - 1)),
            base: [[0; 2]; D],
            w: [[[0.0; 3]; 2]; D],
            off: [[[0.0; 3]; 2]; D],
        };
        for d in 0..D {
            for kind in 0..2 {
                let shift = if kind == 1 { 0.0 } else { 0.5 };
                let g = x[d] / dx - shift;
                let b = (g - 0.5).floor();
                k.w[d][kind] = quadratic_weights(g - b);
                let b = (b.max(0.0) as usize).min(n + kind - 3);
                k.base[d][kind] = b;
                for j in 0..3 {
                    k.off[d][kind][j] = ((b + j) as f32 + shift) * dx - x[d];
                }
            }
        }
        k
    }

    /// [`Self::new`] with `LANES8` in one 8-float vector ([`Self::new_lanes`], x86-64-v3 only).
    #[inline(always)]
    pub(super) fn at<const LANES8: bool>(x: &SVector<f32, D>, dx: f32, n: usize) -> Self {
        #[cfg(target_arch = "x86_64")]
        if LANES8 {
            // SAFETY: `LANES8` is set in the x86-64-v3 copies only, run on a CPU with AVX2
            return unsafe { Self::new_lanes(x, dx, n) };
        }
        Self::new(x, dx, n)
    }

    /// [`Self::new`] with the axes and both kinds in the lanes of one 8-float vector (AVX2; lane
    /// `2·d + kind`), each lane the same f32 operations in the same order: the same bits (a test
    /// compares them).
    ///
    /// # Safety
    /// On a CPU with AVX2 only.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub(super) unsafe fn new_lanes(x: &SVector<f32, D>, dx: f32, n: usize) -> Self {
        use core::arch::x86_64::{
            _mm256_add_ps, _mm256_cvttps_epi32, _mm256_div_ps, _mm256_floor_ps, _mm256_max_ps,
            _mm256_min_ps, _mm256_mul_ps, _mm256_set1_ps, _mm256_setr_ps, _mm256_storeu_ps,
            _mm256_storeu_si256, _mm256_sub_ps,
        };
        // SAFETY: the caller runs this on a CPU with AVX2
        unsafe {
            let xd = |d: usize| if d < D { x[d] } else { 0.0 };
            let xv = _mm256_setr_ps(xd(0), xd(0), xd(1), xd(1), xd(2), xd(2), 0.0, 0.0);
            let shift = _mm256_setr_ps(0.5, 0.0, 0.5, 0.0, 0.5, 0.0, 0.5, 0.0);
            let (l0, l1) = ((n - 3) as f32, (n - 2) as f32);
            let lim = _mm256_setr_ps(l0, l1, l0, l1, l0, l1, l0, l1);
            let s = _mm256_set1_ps;
            let g = _mm256_sub_ps(_mm256_div_ps(xv, s(dx)), shift);
            let b = _mm256_floor_ps(_mm256_sub_ps(g, s(0.5)));
            // quadratic_weights(g - b), its operations in its order
            let f = _mm256_sub_ps(g, b);
            let (h, t) = (_mm256_sub_ps(s(1.5), f), _mm256_sub_ps(f, s(1.0)));
            let q = _mm256_sub_ps(f, s(0.5));
            let w = [
                _mm256_mul_ps(_mm256_mul_ps(s(0.5), h), h),
                _mm256_sub_ps(s(0.75), _mm256_mul_ps(t, t)),
                _mm256_mul_ps(_mm256_mul_ps(s(0.5), q), q),
            ];
            // the base clamped to the grid (a NaN to 0, as `max` takes the second operand)
            let bc = _mm256_min_ps(_mm256_max_ps(b, s(0.0)), lim);
            let off = |j: f32| {
                _mm256_sub_ps(
                    _mm256_mul_ps(_mm256_add_ps(_mm256_add_ps(bc, s(j)), shift), s(dx)),
                    xv,
                )
            };
            let off = [off(0.0), off(1.0), off(2.0)];
            let mut lanes = [[0.0f32; 8]; 6];
            for j in 0..3 {
                _mm256_storeu_ps(lanes[j].as_mut_ptr(), w[j]);
                _mm256_storeu_ps(lanes[3 + j].as_mut_ptr(), off[j]);
            }
            let mut base = [0i32; 8];
            _mm256_storeu_si256(base.as_mut_ptr().cast(), _mm256_cvttps_epi32(bc));
            // the cell from the node grid's lanes (`x/dx − 0` is `x/dx`), clamped as `as usize` and `min` do
            let last = s((n - 1) as f32);
            let mut cell = [0i32; 8];
            let c = _mm256_min_ps(_mm256_max_ps(g, s(0.0)), last);
            _mm256_storeu_si256(cell.as_mut_ptr().cast(), _mm256_cvttps_epi32(c));
            let mut k = Kernel {
                cell: std::array::from_fn(|d| cell[2 * d + 1] as usize),
                base: [[0; 2]; D],
                w: [[[0.0; 3]; 2]; D],
                off: [[[0.0; 3]; 2]; D],
            };
            for d in 0..D {
                for kind in 0..2 {
                    let l = 2 * d + kind;
                    k.base[d][kind] = base[l] as usize;
                    k.w[d][kind] = [lanes[0][l], lanes[1][l], lanes[2][l]];
                    k.off[d][kind] = [lanes[3][l], lanes[4][l], lanes[5][l]];
                }
            }
            k
        }
    }

    /// Per axis on the grid of `kinds` and `stride`: the 3 nodes' parts of the flat index, their
    /// weights and offsets [m], and the nodes the last axis has (in 2D a third axis of one node,
    /// weight 1, offset 0, so one loop serves both).
    #[inline(always)]
    fn axes(&self, kinds: [usize; D], stride: &[usize; D]) -> Axes {
        let (mut i, mut w, mut o) = ([[0usize; 3]; 3], [[1.0f32, 0.0, 0.0]; 3], [[0.0f32; 3]; 3]);
        for d in 0..D {
            let k = kinds[d];
            i[d] = std::array::from_fn(|j| (self.base[d][k] + j) * stride[d]);
            w[d] = self.w[d][k];
            o[d] = self.off[d][k];
        }
        (i, w, o, if D == 3 { 3 } else { 1 })
    }
}

impl<const D: usize> Kernel<D> {
    /// The stencil's rows along the last axis (whose three nodes are contiguous, stride 1): per row its
    /// first node's flat index, the product of the other axes' weights (times `scale`) and the sum of
    /// their affine terms `t` (added to `u`), in a fixed order; and the last axis' weights and affine terms.
    #[inline(always)]
    fn rows(
        &self,
        kinds: [usize; D],
        stride: &[usize; D],
        scale: f32,
        u: f32,
        t: &[[f32; 3]; 3],
    ) -> Rows {
        let ([i0, i1, i2], [w0, w1, w2], _, _) = self.axes(kinds, stride);
        let mut rows = [(0usize, 0.0f32, 0.0f32); 9];
        if D == 3 {
            for a in 0..3 {
                let (mw0, u0) = (scale * w0[a], u + t[0][a]);
                for b in 0..3 {
                    rows[3 * a + b] = (i0[a] + i1[b] + i2[0], mw0 * w1[b], u0 + t[1][b]);
                }
            }
            (rows, 9, w2, t[2])
        } else {
            for a in 0..3 {
                rows[a] = (i0[a] + i1[0], scale * w0[a], u + t[0][a]);
            }
            (rows, 3, w1, t[1])
        }
    }

    /// The cell-centred masses' p2g of one particle of mass `m` [kg], row by row of the stencil.
    #[inline(always)]
    fn scatter_cells(&self, stride: &[usize; D], m: f32, cell: &mut [f32]) {
        let zero = [[0.0f32; 3]; 3];
        let (rows, count, wl, _) = self.rows(kinds(None), stride, 1.0, 0.0, &zero);
        for &(start, rw, _) in &rows[..count] {
            let dst: &mut [f32; 3] = (&mut cell[start..start + 3]).try_into().unwrap();
            for j in 0..3 {
                dst[j] += m * (rw * wl[j]);
            }
        }
    }

    /// p2g of one particle on one grid: adds `m·w` and `m·w·(u + Σ_d c_d·(x_i − x_p)_d)` to each of its
    /// 3^D nodes' `[mass, momentum]` (the affine term summed per axis, the mass folded into the first
    /// axis' weights), row by row of the stencil along the last axis. (Adding a row as one 8-float
    /// vector was measured slower: a particle's wide store and its neighbour's overlapping load defeat
    /// the store-to-load forwarding.)
    #[inline(always)]
    fn scatter(
        &self,
        kinds: [usize; D],
        stride: &[usize; D],
        m: f32,
        u: f32,
        c: &[f32; D],
        grid: &mut [[f32; 2]],
    ) {
        let (_, _, o, _) = self.axes(kinds, stride);
        // the affine term's part per axis and node: c_d·(x_i − x_p)_d
        let t: [[f32; 3]; 3] = std::array::from_fn(|d| {
            std::array::from_fn(|j| if d < D { c[d] * o[d][j] } else { 0.0 })
        });
        let (rows, count, wl, tl) = self.rows(kinds, stride, m, u, &t);
        for &(start, rw, ru) in &rows[..count] {
            let dst: &mut [[f32; 2]; 3] = (&mut grid[start..start + 3]).try_into().unwrap();
            for j in 0..3 {
                let w = rw * wl[j];
                dst[j][0] += w;
                dst[j][1] += w * (ru + tl[j]);
            }
        }
    }

    /// g2p of one particle from one grid: `(Σ w·u, Σ w·u·(x_i − x_p))`, contracted one axis at a time.
    #[inline(always)]
    pub(super) fn gather(
        &self,
        kinds: [usize; D],
        stride: &[usize; D],
        grid: &[f32],
    ) -> (f32, [f32; D]) {
        let ([i0, i1, i2], [w0, w1, w2], [o0, o1, o2], last) = self.axes(kinds, stride);
        let (mut v, mut c) = (0.0f32, [0.0f32; D]);
        for a in 0..3 {
            // over the second and last axes: Σ w u, Σ w u o1, Σ w u o2
            let (mut s, mut s1, mut s2) = (0.0f32, 0.0f32, 0.0f32);
            for b in 0..3 {
                let iab = i0[a] + i1[b];
                let (mut t, mut t2) = (0.0f32, 0.0f32);
                for k in 0..last {
                    let wu = w2[k] * grid[iab + i2[k]];
                    t += wu;
                    t2 += wu * o2[k];
                }
                s += w1[b] * t;
                s1 += w1[b] * o1[b] * t;
                s2 += w1[b] * t2;
            }
            v += w0[a] * s;
            c[0] += w0[a] * o0[a] * s;
            c[1] += w0[a] * s1;
            if D == 3 {
                c[D - 1] += w0[a] * s2;
            }
        }
        (v, c)
    }
}

/// The kinds of a velocity component's face grid: its own axis on the nodes (`None`: the cell centres).
pub(super) fn kinds<const D: usize>(axis: Option<usize>) -> [usize; D] {
    std::array::from_fn(|d| usize::from(Some(d) == axis))
}

/// Calls `f(flat index, index)` for every node of a grid of shape `s`, row-major, stepping the index like an odometer.
pub(super) fn for_each_node<const D: usize>(s: &[usize; D], mut f: impl FnMut(usize, &[usize; D])) {
    let total: usize = s.iter().product();
    let mut idx = [0usize; D];
    for flat in 0..total {
        f(flat, &idx);
        let mut d = D;
        while d > 0 {
            d -= 1;
            idx[d] += 1;
            if idx[d] < s[d] {
                break;
            }
            idx[d] = 0;
        }
    }
}

/// One part of the particles' p2g, into grids of its own: per velocity
/// component the face momenta [kg·m/s] and masses [kg], and the cell-centred
/// masses (the smoothed density). The particles go in two parts, fixed by
/// their count, whatever the threads, and the parts are summed in one
/// order: the same bits on one thread or two.
#[derive(Clone, Debug, Default)]
pub(super) struct Part {
    /// Per component, per face: `[mass, momentum]` (one cache line holds both).
    pub(super) faces: Vec<Vec<[f32; 2]>>,
    pub(super) cell: Vec<f32>,
    /// Per cell: whether a particle of the part is in it (cells in the walls left out).
    pub(super) held: Vec<bool>,
}

impl Part {
    /// p2g of `particles` into this part's grids (zeroed first), and the cells they are in (away from
    /// the walls), with the compiled copy `isa` names ([`crate::isa`]: the same bits either way).
    pub(super) fn scatter<const D: usize>(
        &mut self,
        isa: Isa,
        particles: &[Particle<D>],
        g: Grid,
        dt: f32,
    ) {
        // SAFETY: the solver chooses X86_64V3 only on a CPU that has its features
        #[cfg(target_arch = "x86_64")]
        if isa == Isa::X86_64V3 {
            return unsafe { self.scatter_v3(particles, g, dt) };
        }
        let _ = isa;
        self.scatter_body::<D, false>(particles, g, dt);
    }

    x86_64_v3! {
        /// [`Self::scatter_body`] compiled for x86-64-v3.
        ///
        /// # Safety
        /// On a CPU with the x86-64-v3 features only.
        unsafe fn scatter_v3<const D: usize>(&mut self, particles: &[Particle<D>], g: Grid, dt: f32) {
            self.scatter_body::<D, true>(particles, g, dt);
        }
    }

    /// The p2g; with `LANES8` each particle's kernel in one vector ([`Kernel::new_lanes`]; x86-64-v3 only).
    #[inline(always)]
    fn scatter_body<const D: usize, const LANES8: bool>(
        &mut self,
        particles: &[Particle<D>],
        g: Grid,
        dt: f32,
    ) {
        let Grid { n, dx, .. } = g;
        let cells = n.pow(D as u32);
        if self.cell.len() != cells {
            self.faces = (0..D)
                .map(|a| vec![[0.0; 2]; shape::<D>(n, Some(a)).iter().product()])
                .collect();
            self.cell = vec![0.0; cells];
            self.held = vec![false; cells];
        }
        self.faces.iter_mut().for_each(|g| g.fill([0.0; 2]));
        self.cell.fill(0.0);
        self.held.fill(false);
        let st_c = strides(&shape::<D>(n, None));
        let st_f: [[usize; D]; D] = std::array::from_fn(|a| strides(&shape::<D>(n, Some(a))));
        for p in particles {
            let k = Kernel::at::<LANES8>(&p.x, dx, n);
            if !g.in_walls(&k.cell) {
                self.held[(0..D).map(|d| k.cell[d] * st_c[d]).sum::<usize>()] = true;
            }
            k.scatter_cells(&st_c, p.mass, &mut self.cell);
            for a in 0..D {
                let u = p.v[a] + dt * p.ext[a];
                let c: [f32; D] = std::array::from_fn(|d| p.c[(a, d)]);
                k.scatter(kinds(Some(a)), &st_f[a], p.mass, u, &c, &mut self.faces[a]);
            }
        }
    }
}

/// g2p (APIC) and the move of a chunk of particles from the face velocities `vel` of the grid `g`, with
/// the compiled copy `isa` names ([`crate::isa`]: the same bits either way): `v_a = Σ w u_a`,
/// `c_a = (4/dx²)·Σ w u_a (x_i − x_p)`, `x ← x + dt·v` kept inside the walls ([`Grid::inside`]).
pub(super) fn g2p_chunk<const D: usize>(
    isa: Isa,
    chunk: &mut [Particle<D>],
    vel: &[Vec<f32>],
    g: Grid,
    dt: f32,
) {
    // SAFETY: the solver chooses X86_64V3 only on a CPU that has its features
    #[cfg(target_arch = "x86_64")]
    if isa == Isa::X86_64V3 {
        return unsafe { g2p_chunk_v3(chunk, vel, g, dt) };
    }
    let _ = isa;
    g2p_chunk_body::<D, false>(chunk, vel, g, dt);
}

x86_64_v3! {
    /// [`g2p_chunk_body`] compiled for x86-64-v3.
    ///
    /// # Safety
    /// On a CPU with the x86-64-v3 features only.
    unsafe fn g2p_chunk_v3<const D: usize>(chunk: &mut [Particle<D>], vel: &[Vec<f32>], g: Grid, dt: f32) {
        g2p_chunk_body::<D, true>(chunk, vel, g, dt);
    }
}

/// The particles a 3D g2p takes at once, one per lane of a [`V4`].
pub(super) const LANES: usize = 4;

/// g2p of a chunk: in 3D [`LANES`] particles at once ([`gather_lanes`]), and one at a time the
/// particles past the last full set and in 2D; the same bits either way.
/// With `LANES8` each particle's kernel is made in one vector ([`Kernel::new_lanes`]; x86-64-v3 only).
#[inline(always)]
fn g2p_chunk_body<const D: usize, const LANES8: bool>(
    chunk: &mut [Particle<D>],
    vel: &[Vec<f32>],
    g: Grid,
    dt: f32,
) {
    let Grid { n, dx, .. } = g;
    let (lo, hi) = g.inside();
    let apic = 4.0 / (dx * dx);
    let st_f: [[usize; D]; D] = std::array::from_fn(|a| strides(&shape::<D>(n, Some(a))));
    let mut quads = chunk.chunks_exact_mut(if D == 3 { LANES } else { usize::MAX });
    for quad in &mut quads {
        // arrays written out rather than made by `array::from_fn` or `map`, whose closures LLVM may
        // leave out of line (and out of the x86-64-v3 copy)
        let x = |l: usize| &quad[l].x;
        let k = [
            Kernel::at::<LANES8>(x(0), dx, n),
            Kernel::at::<LANES8>(x(1), dx, n),
            Kernel::at::<LANES8>(x(2), dx, n),
            Kernel::at::<LANES8>(x(3), dx, n),
        ];
        for a in 0..D {
            let (v, c) = gather_lanes(&k, kinds(Some(a)), &st_f[a], &vel[a]);
            let (v, c) = (
                v.to_array(),
                [c[0].to_array(), c[1].to_array(), c[2].to_array()],
            );
            for (l, p) in quad.iter_mut().enumerate() {
                p.v[a] = v[l];
                for d in 0..D {
                    p.c[(a, d)] = apic * c[d][l];
                }
            }
        }
        for p in quad.iter_mut() {
            move_on(p, dt, (lo, hi));
        }
    }
    for p in quads.into_remainder() {
        let k = Kernel::at::<LANES8>(&p.x, dx, n);
        for a in 0..D {
            let (va, ca) = k.gather(kinds(Some(a)), &st_f[a], &vel[a]);
            p.v[a] = va;
            for d in 0..D {
                p.c[(a, d)] = apic * ca[d];
            }
        }
        move_on(p, dt, (lo, hi));
    }
}

/// A particle moves on at its velocity for `dt` [s], kept within `(lo, hi)` on every axis (g2p's move
/// and a drift frame's).
#[inline(always)]
pub(super) fn move_on<const D: usize>(p: &mut Particle<D>, dt: f32, (lo, hi): (f32, f32)) {
    for d in 0..D {
        p.x[d] = (p.x[d] + dt * p.v[d]).clamp(lo, hi);
    }
}

/// Three values per particle, one vector per value with one lane per particle.
#[inline(always)]
fn lanes(v: [[f32; 3]; LANES]) -> [V4; 3] {
    let p = |[a, b, c]: [f32; 3]| V4::load(&[a, b, c, 0.0]);
    let t = V4::transpose([p(v[0]), p(v[1]), p(v[2]), p(v[3])]);
    [t[0], t[1], t[2]]
}

/// The row `(a, b)` of a particle's stencil (node indices `i` per axis) along the last axis: its
/// three nodes and an unused fourth float.
#[inline(always)]
fn row(grid: &[f32], i: &[[usize; 3]; 3], a: usize, b: usize) -> V4 {
    let start = i[0][a] + i[1][b] + i[2][0];
    match grid.get(start..start + 4) {
        Some(r) => V4::load(r.try_into().unwrap()),
        // the grid's last row
        None => V4::load(&[grid[start], grid[start + 1], grid[start + 2], 0.0]),
    }
}

/// [`Kernel::gather`] of [`LANES`] particles of a 3D grid at once, one per lane, each lane the same
/// f32 operations in the same order (the same bits): each row of a particle's stencil along the
/// last axis is one 4-float load (the fourth float unused), and the particles' rows are transposed
/// into one vector per node of the row.
#[inline(always)]
pub(super) fn gather_lanes<const D: usize>(
    k: &[Kernel<D>; LANES],
    kinds: [usize; D],
    stride: &[usize; D],
    grid: &[f32],
) -> (V4, [V4; 3]) {
    let ax = [
        k[0].axes(kinds, stride),
        k[1].axes(kinds, stride),
        k[2].axes(kinds, stride),
        k[3].axes(kinds, stride),
    ];
    // per axis and node: the particles' weights and offsets, one per lane
    let w = |d: usize| lanes([ax[0].1[d], ax[1].1[d], ax[2].1[d], ax[3].1[d]]);
    let o = |d: usize| lanes([ax[0].2[d], ax[1].2[d], ax[2].2[d], ax[3].2[d]]);
    let (w, o) = ([w(0), w(1), w(2)], [o(0), o(1), o(2)]);
    let zero = V4::splat(0.0);
    let (mut v, mut c) = (zero, [zero; 3]);
    for a in 0..3 {
        let (mut s, mut s1, mut s2) = (zero, zero, zero);
        for b in 0..3 {
            let r = V4::transpose([
                row(grid, &ax[0].0, a, b),
                row(grid, &ax[1].0, a, b),
                row(grid, &ax[2].0, a, b),
                row(grid, &ax[3].0, a, b),
            ]);
            let (mut t, mut t2) = (zero, zero);
            for j in 0..3 {
                let wu = w[2][j] * r[j];
                t = t + wu;
                t2 = t2 + wu * o[2][j];
            }
            s = s + w[1][b] * t;
            s1 = s1 + w[1][b] * o[1][b] * t;
            s2 = s2 + w[1][b] * t2;
        }
        v = v + w[0][a] * s;
        c[0] = c[0] + w[0][a] * o[0][a] * s;
        c[1] = c[1] + w[0][a] * s1;
        c[2] = c[2] + w[0][a] * s2;
    }
    (v, c)
}

#[cfg(all(test, target_arch = "x86_64"))]
mod tests {
    use super::*;

    fn same<const D: usize>(x: SVector<f32, D>, dx: f32, n: usize) {
        let a = Kernel::new(&x, dx, n);
        // SAFETY: AVX2 is present (checked by the caller)
        let b = unsafe { Kernel::new_lanes(&x, dx, n) };
        let bits = |k: &Kernel<D>| {
            let w = k.w.iter().flatten().flatten().map(|v| v.to_bits());
            let o = k.off.iter().flatten().flatten().map(|v| v.to_bits());
            (k.cell, k.base, w.chain(o).collect::<Vec<u32>>())
        };
        assert_eq!(bits(&a), bits(&b), "x = {x:?}, n = {n}");
    }

    #[test]
    fn the_kernel_in_one_vector_gives_the_bits_of_the_scalar_one() {
        if !std::is_x86_feature_detected!("avx2") {
            return; // nothing to compare: the vector kernel runs on AVX2 CPUs only
        }
        let mut seed = 5u32;
        let mut rand = move || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (seed >> 8) as f32 / (1u32 << 24) as f32
        };
        for n in [8, 13, 56, 128] {
            let dx = 1.0 / n as f32;
            for _ in 0..2000 {
                // across the grid, on its nodes and cell centres, at and past its ends
                let mut coord = || match rand() {
                    r if r < 0.1 => (rand() * n as f32).floor() * dx,
                    r if r < 0.2 => ((rand() * n as f32).floor() + 0.5) * dx,
                    r if r < 0.25 => -0.0,
                    r if r < 0.3 => 1.0 - 1e-6,
                    r if r < 0.35 => 1.0 + rand(),
                    r if r < 0.4 => -rand(),
                    _ => rand(),
                };
                same::<2>(SVector::from_fn(|_, _| coord()), dx, n);
                same::<3>(SVector::from_fn(|_, _| coord()), dx, n);
            }
        }
    }
}
