//! [`SandBatch`]: the g2p sand update of sixteen particles at once, one per
//! SIMD lane.

use nalgebra::SMatrix;

use super::SandModel;
use super::update_2d::advance_2d;
use super::update_3d::advance_3d;
use crate::isa::{Isa, x86_64_v3};
use crate::material::lanes::{FL, LANES, Real};
use crate::particles::Particle;
use crate::v4::V4;

/// Sand particles gathered for their g2p material update, one lane of an
/// [`FL`] each (structure of arrays), so that [`SandBatch::run`] updates
/// sixteen at once with SIMD instructions: the elastic predictor
/// `F* = (I + Δt·C)·F`, then [`advance_2d`] or [`advance_3d`] (written in
/// [`Real`] arithmetic with selects instead of branches and
/// [`vmath`](crate::material::vmath) instead of libm) and the health checks,
/// all on [`FL`]. Each lane gives the bits of the same update on one `f32`
/// particle.
///
/// Use: [`push`](Self::push) each particle's F, C and `vc` with an index of
/// the caller's; when it reports the batch full, and once at the end,
/// [`run`](Self::run) it, read the lanes with [`lane`](Self::lane) and
/// [`clear`](Self::clear) it. Lanes past [`len`](Self::len) hold finite
/// leftovers that are computed and ignored. Matrices are row-major, `D ≤ 3`.
pub(crate) struct SandBatch {
    len: usize,
    at: [u32; LANES],
    /// The new velocity gradient C [1/s].
    c: [FL; 9],
    /// In: the elastic F; after `run`: the new one.
    f: [FL; 9],
    vc: FL,
    /// After `run`: the Kirchhoff stress [Pa].
    tau: [FL; 9],
}

/// Where [`SandBatch::write_lanes`] writes: the particle at an index
/// pushed with a lane (a slice, or g2p's view of the particle storage).
pub(crate) trait ParticleSink<const D: usize> {
    /// The particle at `i`. Panics if `i` is out of range.
    fn at(&mut self, i: usize) -> &mut Particle<D>;
}

impl<const D: usize> ParticleSink<D> for [Particle<D>] {
    #[inline(always)]
    fn at(&mut self, i: usize) -> &mut Particle<D> {
        &mut self[i]
    }
}

/// What g2p's health check needs of a [`SandBatch`]'s lanes in use.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct SandHealth {
    /// Every new F, volume correction and stress is finite.
    pub(crate) finite: bool,
    /// Some new F has `det F ≤ 0` (or NaN).
    pub(crate) inverted: bool,
}

impl SandBatch {
    /// An empty batch (its lanes hold identity F and zero C).
    pub(crate) fn new() -> Self {
        let mut f = [FL::splat(0.0); 9];
        for k in [0, 4, 8] {
            f[k] = FL::splat(1.0);
        }
        SandBatch {
            len: 0,
            at: [0; LANES],
            c: [FL::splat(0.0); 9],
            f,
            vc: FL::splat(0.0),
            tau: [FL::splat(0.0); 9],
        }
    }

    /// Lanes in use.
    pub(crate) fn len(&self) -> usize {
        self.len
    }

    /// Adds a particle (caller's index `at`, elastic F, new C, volume
    /// correction); returns whether the batch is now full. Panics if it was
    /// full.
    #[inline(always)]
    pub(crate) fn push<const D: usize>(
        &mut self,
        at: u32,
        f: &SMatrix<f32, D, D>,
        c: &SMatrix<f32, D, D>,
        vc: f32,
    ) -> bool {
        let l = self.len;
        self.at[l] = at;
        for r in 0..D {
            for k in 0..D {
                self.f[r * D + k].0[l] = f[(r, k)];
                self.c[r * D + k].0[l] = c[(r, k)];
            }
        }
        self.vc.0[l] = vc;
        self.len += 1;
        self.len == LANES
    }

    /// The g2p update of every lane with time step `dt` [s]: elastic
    /// predictor, return mapping (Klár et al. 2016, Sec. 7; see
    /// [`advance_2d`], [`advance_3d`]); afterwards the lanes hold the new F,
    /// `vc` and the stress, and [`len`](Self::len) is still the count pushed.
    /// Returns the health of the lanes in use.
    ///
    /// Runs the copy compiled for `m.isa` (`crate::isa`); either gives the
    /// same bits. Not inlined into the frame loop: its own function keeps
    /// the lanes in registers.
    pub(crate) fn run<const D: usize>(&mut self, m: &SandModel, dt: f32) -> SandHealth {
        #[cfg(target_arch = "x86_64")]
        if m.isa == Isa::X86_64V3 {
            // SAFETY: an `Isa` in a `SandModel` is available on this CPU
            return unsafe { self.run_v3::<D>(m, dt) };
        }
        self.run_portable::<D>(m, dt)
    }

    #[inline(never)]
    fn run_portable<const D: usize>(&mut self, m: &SandModel, dt: f32) -> SandHealth {
        self.run_body::<D>(m, dt)
    }

    x86_64_v3! {
        #[inline(never)]
        unsafe fn run_v3<const D: usize>(&mut self, m: &SandModel, dt: f32) -> SandHealth {
            self.run_body::<D>(m, dt)
        }
    }

    #[inline(always)]
    fn run_body<const D: usize>(&mut self, m: &SandModel, dt: f32) -> SandHealth {
        // lanes not in use repeat lane 0, so that only the particles pushed
        // decide the batch's route in 3D (`advance_3d`)
        if self.len > 0 {
            for l in self.len..LANES {
                for k in 0..D * D {
                    self.f[k].0[l] = self.f[k].0[0];
                    self.c[k].0[l] = self.c[k].0[0];
                }
                self.vc.0[l] = self.vc.0[0];
            }
        }
        // F* = (I + Δt·C)·F
        let dtv = FL::splat(dt);
        let mut ft = [FL::splat(0.0); 9];
        for r in 0..D {
            for k in 0..D {
                let mut acc = FL::splat(0.0);
                for j in 0..D {
                    let a = self.c[r * D + j] * dtv;
                    let a = if r == j { FL::splat(1.0) + a } else { a };
                    acc = if j == 0 {
                        a * self.f[j * D + k]
                    } else {
                        acc + a * self.f[j * D + k]
                    };
                }
                ft[r * D + k] = acc;
            }
        }
        let det = if D == 2 {
            let (f, vc, tau) = advance_2d(&[ft[0], ft[1], ft[2], ft[3]], self.vc, m);
            self.f[..4].copy_from_slice(&f);
            self.tau[..4].copy_from_slice(&tau);
            self.vc = vc;
            f[0] * f[3] - f[1] * f[2]
        } else {
            let (f, vc, tau) = advance_3d(&ft, self.vc, m);
            (self.f, self.vc, self.tau) = (f, vc, tau);
            f[0] * (f[4] * f[8] - f[5] * f[7]) - f[1] * (f[3] * f[8] - f[5] * f[6])
                + f[2] * (f[3] * f[7] - f[4] * f[6])
        };
        // 0 where F, vc and τ are finite, NaN elsewhere (the stresses' sum is
        // non-finite if one is, or if it overflows: a blow-up too)
        let mut probe = self.vc.zero_if_finite();
        let mut tau_sum = FL::splat(0.0);
        for k in 0..D * D {
            probe = probe + self.f[k].zero_if_finite();
            tau_sum = tau_sum + self.tau[k];
        }
        probe = probe + tau_sum.zero_if_finite();
        let mut health = SandHealth {
            finite: true,
            inverted: false,
        };
        for l in 0..self.len {
            health.finite &= probe.0[l] == 0.0;
            health.inverted |= !(det.0[l] > 0.0);
        }
        health
    }

    /// Lane `l` after [`run`](Self::run): `(at, new F, vc, τ)`.
    #[inline(always)]
    pub(crate) fn lane<const D: usize>(
        &self,
        l: usize,
    ) -> (u32, SMatrix<f32, D, D>, f32, SMatrix<f32, D, D>) {
        let mut f = SMatrix::<f32, D, D>::zeros();
        let mut tau = SMatrix::<f32, D, D>::zeros();
        for r in 0..D {
            for c in 0..D {
                f[(r, c)] = self.f[r * D + c].0[l];
                tau[(r, c)] = self.tau[r * D + c].0[l];
            }
        }
        (self.at[l], f, self.vc.0[l], tau)
    }

    /// After [`run`](Self::run): writes each lane in use to `outp[at]` (`at`
    /// as pushed): its new F, `vc` and stress, the values of
    /// [`lane`](Self::lane). Four lanes at a time through 4 × 4 transposes
    /// ([`V4::transpose`]): one store of four floats where a lane-by-lane
    /// copy makes four scalar stores, which made sand3d's g2p store-bound
    /// (docs/engine.md).
    /// Panics if an `at` is out of range.
    #[inline(always)]
    pub(crate) fn write_lanes<const D: usize>(&self, outp: &mut (impl ParticleSink<D> + ?Sized)) {
        let n = D * D;
        // batch index (row-major) of the particle's column-major entry `i`
        let comp = |i: usize| (i % D) * D + i / D;
        let quads = self.len / 4 * 4;
        for l0 in (0..quads).step_by(4) {
            let at: [usize; 4] = std::array::from_fn(|q| self.at[l0 + q] as usize);
            for (src, tau) in [(&self.f, false), (&self.tau, true)] {
                let mut i = 0;
                while i + 4 <= n {
                    let rows: [V4; 4] = std::array::from_fn(|q| {
                        let lanes: &[f32; 4] = src[comp(i + q)].0[l0..l0 + 4].try_into().unwrap();
                        V4::load(lanes)
                    });
                    for (q, col) in V4::transpose(rows).into_iter().enumerate() {
                        let p = outp.at(at[q]);
                        let m = if tau { &mut p.tau } else { &mut p.f };
                        col.store(&mut m.as_mut_slice()[i..]);
                    }
                    i += 4;
                }
                for i in i..n {
                    for (q, &a) in at.iter().enumerate() {
                        let p = outp.at(a);
                        let m = if tau { &mut p.tau } else { &mut p.f };
                        m.as_mut_slice()[i] = src[comp(i)].0[l0 + q];
                    }
                }
            }
            for (q, &a) in at.iter().enumerate() {
                outp.at(a).vc = self.vc.0[l0 + q];
            }
        }
        for l in quads..self.len {
            let (at, f, vc, tau) = self.lane::<D>(l);
            let p = outp.at(at as usize);
            (p.f, p.vc, p.tau) = (f, vc, tau);
        }
    }

    /// Empties the batch (after its lanes were read).
    pub(crate) fn clear(&mut self) {
        self.len = 0;
    }
}
