//! The projection step's particle-grid transfers on the MAC grid: a
//! particle's quadratic B-spline weights on both grids of each axis, p2g in
//! two fixed parts of the particles, g2p one axis at a time.

use nalgebra::SVector;

use super::{shape, strides};
use crate::kernel::quadratic_weights;
use crate::particles::Particle;

/// Per axis of a 3^D stencil: the nodes' parts of the flat index, weights, offsets [m]; the last axis' node count.
type Axes = ([[usize; 3]; 3], [[f32; 3]; 3], [[f32; 3]; 3], usize);

/// A particle's quadratic B-spline weights on the two grids of each axis:
/// kind 0, the cell centres `(i + ½)·dx`; kind 1, the nodes `i·dx` (a
/// velocity component's own axis on its face grid). Per axis and kind: the
/// stencil's first node (clamped so the stencil stays on the grid), the
/// weights, and the offsets `x_i − x_p` [m].
pub(super) struct Kernel<const D: usize> {
    base: [[usize; 2]; D],
    w: [[[f32; 3]; 2]; D],
    off: [[[f32; 3]; 2]; D],
}

impl<const D: usize> Kernel<D> {
    #[inline(always)]
    pub(super) fn new(x: &SVector<f32, D>, dx: f32, n: usize) -> Self {
        let mut k = Kernel {
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

    /// Calls `f(flat index, weight, offsets)` for the 3^D nodes of the grid
    /// whose axis `d` is of kind `kinds[d]` and whose strides are `stride`,
    /// in a fixed order (the last axis fastest).
    #[inline(always)]
    pub(super) fn each(
        &self,
        kinds: [usize; D],
        stride: &[usize; D],
        mut f: impl FnMut(usize, f32, [f32; D]),
    ) {
        let ([i0, i1, i2], [w0, w1, w2], [o0, o1, o2], last) = self.axes(kinds, stride);
        let mut off = [0.0f32; D];
        for a in 0..3 {
            off[0] = o0[a];
            for b in 0..3 {
                off[1] = o1[b];
                let (wab, iab) = (w0[a] * w1[b], i0[a] + i1[b]);
                for c in 0..last {
                    if D == 3 {
                        off[D - 1] = o2[c];
                    }
                    f(iab + i2[c], wab * w2[c], off);
                }
            }
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
    /// p2g of one particle on one grid: adds `m·w` and `m·w·(u + Σ_d c_d·(x_i − x_p)_d)` to each of its
    /// 3^D nodes' `[mass, momentum]` (the affine term summed per axis, the mass folded into the first
    /// axis' weights).
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
        let ([i0, i1, i2], [w0, w1, w2], o, last) = self.axes(kinds, stride);
        // the affine term's part per axis and node: c_d·(x_i − x_p)_d
        let [t0, t1, t2]: [[f32; 3]; 3] = std::array::from_fn(|d| {
            std::array::from_fn(|j| if d < D { c[d] * o[d][j] } else { 0.0 })
        });
        for a in 0..3 {
            let (mw0, u0) = (m * w0[a], u + t0[a]);
            for b in 0..3 {
                let (wab, uab, iab) = (mw0 * w1[b], u0 + t1[b], i0[a] + i1[b]);
                for c in 0..last {
                    let w = wab * w2[c];
                    let f = &mut grid[iab + i2[c]];
                    f[0] += w;
                    f[1] += w * (uab + t2[c]);
                }
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
}

impl Part {
    pub(super) fn scatter<const D: usize>(
        &mut self,
        particles: &[Particle<D>],
        n: usize,
        dx: f32,
        dt: f32,
    ) {
        let cells = n.pow(D as u32);
        if self.cell.len() != cells {
            self.faces = (0..D)
                .map(|a| vec![[0.0; 2]; shape::<D>(n, Some(a)).iter().product()])
                .collect();
            self.cell = vec![0.0; cells];
        }
        self.faces.iter_mut().for_each(|g| g.fill([0.0; 2]));
        self.cell.fill(0.0);
        let st_c = strides(&shape::<D>(n, None));
        let st_f: [[usize; D]; D] = std::array::from_fn(|a| strides(&shape::<D>(n, Some(a))));
        for p in particles {
            let k = Kernel::new(&p.x, dx, n);
            let cell = &mut self.cell;
            k.each(kinds(None), &st_c, |i, w, _| cell[i] += p.mass * w);
            for a in 0..D {
                let u = p.v[a] + dt * p.ext[a];
                let c: [f32; D] = std::array::from_fn(|d| p.c[(a, d)]);
                k.scatter(kinds(Some(a)), &st_f[a], p.mass, u, &c, &mut self.faces[a]);
            }
        }
    }
}
