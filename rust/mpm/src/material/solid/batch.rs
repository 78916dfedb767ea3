//! [`SolidBatch`]: the g2p update of sixteen solid particles of one
//! parameter set at once, one per SIMD lane, as sand's
//! [`SandBatch`](crate::material::sand::SandBatch).

use nalgebra::SMatrix;

use super::{Model, trial, update_lanes};
use crate::isa::{Isa, x86_64_v3};
use crate::material::lanes::{FL, LANES, Real};
use crate::material::sand::{ParticleSink, SandHealth};
use crate::v4::V4;

/// Solid particles (elastic, snow, viscoplastic) of one parameter set
/// gathered for their g2p update, one lane of an [`FL`] each, so that
/// [`run`](Self::run) updates sixteen at once ([`update_lanes`] on
/// [`FL`]). Each lane gives the bits of [`super::advance`] on that
/// particle alone (no lane's route depends on another's values).
///
/// Use as [`SandBatch`](crate::material::sand::SandBatch): [`push`](Self::push)
/// each particle's F, C and `J` with an index of the caller's; when full,
/// and once at the end, [`run`](Self::run), [`write_lanes`](Self::write_lanes)
/// and [`clear`](Self::clear). Matrices are row-major, `D ≤ 3`.
pub(crate) struct SolidBatch {
    len: usize,
    at: [u32; LANES],
    c: [FL; 9],
    /// In: F; after `run`: the new one.
    f: [FL; 9],
    /// In: the particle's `J` (snow's `J_P`); after `run`: the new one.
    j: FL,
    /// After `run`: the Kirchhoff stress [Pa].
    tau: [FL; 9],
}

impl SolidBatch {
    /// An empty batch (its lanes hold identity F, zero C, `J` = 1).
    pub(crate) fn new() -> Self {
        let mut f = [FL::splat(0.0); 9];
        for k in [0, 4, 8] {
            f[k] = FL::splat(1.0);
        }
        SolidBatch {
            len: 0,
            at: [0; LANES],
            c: [FL::splat(0.0); 9],
            f,
            j: FL::splat(1.0),
            tau: [FL::splat(0.0); 9],
        }
    }

    /// Lanes in use.
    pub(crate) fn len(&self) -> usize {
        self.len
    }

    /// Adds a particle (caller's index `at`, F, new C, `J`); returns whether
    /// the batch is now full. Panics if it was full.
    #[inline(always)]
    pub(crate) fn push<const D: usize>(
        &mut self,
        at: u32,
        f: &SMatrix<f32, D, D>,
        c: &SMatrix<f32, D, D>,
        j: f32,
    ) -> bool {
        let l = self.len;
        self.at[l] = at;
        for r in 0..D {
            for k in 0..D {
                self.f[r * D + k].0[l] = f[(r, k)];
                self.c[r * D + k].0[l] = c[(r, k)];
            }
        }
        self.j.0[l] = j;
        self.len += 1;
        self.len == LANES
    }

    /// The g2p update of every lane under model `m` with time step `dt`
    /// [s], in the copy compiled for `isa` (either gives the same bits).
    /// Returns the health of the lanes in use (`finite` also requires
    /// `J > 0`).
    pub(crate) fn run<const D: usize>(&mut self, m: &Model, isa: Isa, dt: f32) -> SandHealth {
        #[cfg(target_arch = "x86_64")]
        if isa == Isa::X86_64V3 {
            // SAFETY: the solver's `Isa` is available on this CPU
            return unsafe { self.run_v3::<D>(m, dt) };
        }
        let _ = isa;
        self.run_portable::<D>(m, dt)
    }

    #[inline(never)]
    fn run_portable<const D: usize>(&mut self, m: &Model, dt: f32) -> SandHealth {
        self.run_body::<D>(m, dt)
    }

    x86_64_v3! {
        #[inline(never)]
        unsafe fn run_v3<const D: usize>(&mut self, m: &Model, dt: f32) -> SandHealth {
            self.run_body::<D>(m, dt)
        }
    }

    #[inline(always)]
    fn run_body<const D: usize>(&mut self, m: &Model, dt: f32) -> SandHealth {
        // lanes not in use repeat lane 0 (finite leftovers)
        if self.len > 0 {
            for l in self.len..LANES {
                for k in 0..D * D {
                    self.f[k].0[l] = self.f[k].0[0];
                    self.c[k].0[l] = self.c[k].0[0];
                }
                self.j.0[l] = self.j.0[0];
            }
        }
        let ft = trial::<FL, D>(&self.f, &self.c, dt);
        let (f, j, tau) = super::keep_uninverted::<FL, D>(
            m,
            (&self.f, self.j),
            update_lanes::<FL, D>(m, &ft, self.j, dt),
        );
        (self.f, self.j, self.tau) = (f, j, tau);
        let det = super::update::det::<FL, D>(&f);
        let mut probe = j.zero_if_finite();
        let mut tau_sum = FL::splat(0.0);
        for k in 0..D * D {
            probe = probe + f[k].zero_if_finite();
            tau_sum = tau_sum + tau[k];
        }
        probe = probe + tau_sum.zero_if_finite();
        let mut health = SandHealth {
            finite: true,
            inverted: false,
        };
        for l in 0..self.len {
            health.finite &= probe.0[l] == 0.0 && j.0[l] > 0.0;
            health.inverted |= !(det.0[l] > 0.0);
        }
        health
    }

    /// After [`run`](Self::run): writes each lane in use to `outp[at]`: its
    /// new F, `J` and stress. Four lanes at a time through 4 × 4 transposes
    /// (as sand's `write_lanes`).
    #[inline(always)]
    pub(crate) fn write_lanes<const D: usize>(&self, outp: &mut (impl ParticleSink<D> + ?Sized)) {
        let n = D * D;
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
                outp.at(a).j = self.j.0[l0 + q];
            }
        }
        for l in quads..self.len {
            let p = outp.at(self.at[l] as usize);
            for r in 0..D {
                for c in 0..D {
                    p.f[(r, c)] = self.f[r * D + c].0[l];
                    p.tau[(r, c)] = self.tau[r * D + c].0[l];
                }
            }
            p.j = self.j.0[l];
        }
    }

    /// Empties the batch (after its lanes were written).
    pub(crate) fn clear(&mut self) {
        self.len = 0;
    }
}
