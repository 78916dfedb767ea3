//! [`Batch`]: the g2p material update of sixteen particles of one parameter
//! set at once, one per SIMD lane, for every model ([`Constitutive`]).

use nalgebra::SMatrix;

use super::Constitutive;
use super::lanes::{FL, LANES, Real};
use super::spectral::det;
use crate::isa::{Isa, x86_64_v3};
use crate::particles::Particle;
use crate::v4::V4;

/// A particle's material state on lanes of `R` (one particle or sixteen):
/// what g2p's update reads and writes. Matrices row-major, the first `D²`
/// entries used.
#[derive(Clone, Copy, Debug)]
pub(crate) struct State<R> {
    /// The deformation gradient F [-] (the elastic part for sand, snow and
    /// the viscoplastic solid; unused by water).
    pub(crate) f: [R; 9],
    /// Water's volume ratio `J`, snow's `J_P` [-] (1 otherwise).
    pub(crate) j: R,
    /// Sand's log-volume correction [-] (0 otherwise).
    pub(crate) vc: R,
    /// Out: the Kirchhoff stress τ [Pa].
    pub(crate) tau: [R; 9],
}

/// Where [`Batch::write_lanes`] writes: the particle at an index pushed
/// with a lane (a slice, or g2p's view of the particle storage).
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

/// What g2p's health check needs of a [`Batch`]'s lanes in use.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct LaneHealth {
    /// Every new F, `J`, volume correction and stress is finite, and `J > 0`.
    pub(crate) finite: bool,
    /// Some new F has `det F ≤ 0` (or NaN) (models with F only).
    pub(crate) inverted: bool,
}

impl LaneHealth {
    /// Healthy: nothing run yet.
    pub(crate) const OK: LaneHealth = LaneHealth {
        finite: true,
        inverted: false,
    };

    /// Both: finite if both are, inverted if either is.
    pub(crate) fn and(&mut self, o: LaneHealth) {
        self.finite &= o.finite;
        self.inverted |= o.inverted;
    }
}

/// Particles of one parameter set gathered for their g2p material update,
/// one lane of an [`FL`] each (structure of arrays), so that
/// [`run`](Self::run) updates sixteen at once with SIMD instructions: the
/// model's [`Constitutive::update_lanes`] (written in [`Real`] arithmetic,
/// selects instead of branches, `material/vmath.rs` instead of libm) and the
/// health checks, all on [`FL`]. Each lane gives the bits of the same update
/// on one `f32` particle, except that sand's 3D route (matrix series or
/// eigenvalues) is chosen for the whole batch (`sand/update_3d.rs`; g2p
/// then keeps a batch within one window of its block, so that the batches
/// are the same for any thread count: `solver/grid.rs`, `G2P_WINDOW`).
///
/// Use: [`push`](Self::push) each particle's state and new C with an index
/// of the caller's (one set per batch: [`set`](Self::set)); when it reports
/// the batch full, and once at the end, [`run`](Self::run) it,
/// [`write_lanes`](Self::write_lanes) and [`clear`](Self::clear). Lanes
/// past [`len`](Self::len) hold finite leftovers that are computed and
/// ignored. Matrices are row-major, `D ≤ 3`.
pub(crate) struct Batch {
    len: usize,
    /// The parameter set of the particles pushed.
    pub(crate) set: u16,
    at: [u32; LANES],
    /// The new velocity gradient C [1/s].
    c: [FL; 9],
    /// In: the particles' state; after `run`: the new one and its stress.
    s: State<FL>,
}

impl Batch {
    /// An empty batch for set `set` (its lanes hold identity F, zero C,
    /// `J` = 1, zero `vc`).
    pub(crate) fn new(set: u16) -> Self {
        let mut f = [FL::splat(0.0); 9];
        for k in [0, 4, 8] {
            f[k] = FL::splat(1.0);
        }
        Batch {
            len: 0,
            set,
            at: [0; LANES],
            c: [FL::splat(0.0); 9],
            s: State {
                f,
                j: FL::splat(1.0),
                vc: FL::splat(0.0),
                tau: [FL::splat(0.0); 9],
            },
        }
    }

    /// Lanes in use.
    pub(crate) fn len(&self) -> usize {
        self.len
    }

    /// Adds a particle (caller's index `at`, its F, `J`, volume correction
    /// and new C); returns whether the batch is now full. Panics if it was
    /// full.
    #[inline(always)]
    pub(crate) fn push<const D: usize>(
        &mut self,
        at: u32,
        (f, j, vc): (&SMatrix<f32, D, D>, f32, f32),
        c: &SMatrix<f32, D, D>,
    ) -> bool {
        let l = self.len;
        self.at[l] = at;
        for r in 0..D {
            for k in 0..D {
                self.s.f[r * D + k].0[l] = f[(r, k)];
                self.c[r * D + k].0[l] = c[(r, k)];
            }
        }
        self.s.j.0[l] = j;
        self.s.vc.0[l] = vc;
        self.len += 1;
        self.len == LANES
    }

    /// The g2p update of every lane under model `m` with time step `dt`
    /// [s]; afterwards the lanes hold the new state and stress, and
    /// [`len`](Self::len) is still the count pushed. Returns the health of
    /// the lanes in use.
    ///
    /// Runs the copy compiled for `isa` (`crate::isa`; it must be
    /// [`available`](Isa::available)); either gives the same bits. Not
    /// inlined into the frame loop: its own function, one per model, keeps
    /// the lanes in registers.
    pub(crate) fn run<const D: usize, M: Constitutive>(
        &mut self,
        m: &M,
        isa: Isa,
        dt: f32,
    ) -> LaneHealth {
        #[cfg(target_arch = "x86_64")]
        if isa == Isa::X86_64V3 {
            // SAFETY: the solver's `Isa` is available on this CPU
            return unsafe { self.run_v3::<D, M>(m, dt) };
        }
        let _ = isa;
        self.run_portable::<D, M>(m, dt)
    }

    #[inline(never)]
    fn run_portable<const D: usize, M: Constitutive>(&mut self, m: &M, dt: f32) -> LaneHealth {
        self.run_body::<D, M>(m, dt)
    }

    x86_64_v3! {
        #[inline(never)]
        unsafe fn run_v3<const D: usize, M: Constitutive>(&mut self, m: &M, dt: f32) -> LaneHealth {
            self.run_body::<D, M>(m, dt)
        }
    }

    #[inline(always)]
    fn run_body<const D: usize, M: Constitutive>(&mut self, m: &M, dt: f32) -> LaneHealth {
        // lanes not in use repeat lane 0, so that only the particles pushed
        // decide the batch's route (sand's in 3D, `sand/update_3d.rs`)
        if self.len > 0 {
            for l in self.len..LANES {
                for k in 0..D * D {
                    self.s.f[k].0[l] = self.s.f[k].0[0];
                    self.c[k].0[l] = self.c[k].0[0];
                }
                self.s.j.0[l] = self.s.j.0[0];
                self.s.vc.0[l] = self.s.vc.0[0];
            }
        }
        m.update_lanes::<FL, D>(&mut self.s, &self.c, dt);
        let s = &self.s;
        // 0 where F, J, vc and τ are finite, NaN elsewhere (the stresses' sum
        // is non-finite if one is, or if it overflows: a blow-up too)
        let mut probe = s.j.zero_if_finite() + s.vc.zero_if_finite();
        let mut tau_sum = FL::splat(0.0);
        for k in 0..D * D {
            if M::HAS_F {
                probe = probe + s.f[k].zero_if_finite();
            }
            tau_sum = tau_sum + s.tau[k];
        }
        probe = probe + tau_sum.zero_if_finite();
        let det = det::<FL, D>(&s.f);
        let mut health = LaneHealth::OK;
        for l in 0..self.len {
            health.finite &= probe.0[l] == 0.0 && s.j.0[l] > 0.0;
            health.inverted |= M::HAS_F && !(det.0[l] > 0.0);
        }
        health
    }

    /// Lane `l` after [`run`](Self::run): `(at, new F, J, vc, τ)`.
    #[cfg(test)]
    pub(crate) fn lane<const D: usize>(
        &self,
        l: usize,
    ) -> (u32, SMatrix<f32, D, D>, f32, f32, SMatrix<f32, D, D>) {
        let f = SMatrix::<f32, D, D>::from_fn(|r, c| self.s.f[r * D + c].0[l]);
        let tau = SMatrix::<f32, D, D>::from_fn(|r, c| self.s.tau[r * D + c].0[l]);
        (self.at[l], f, self.s.j.0[l], self.s.vc.0[l], tau)
    }

    /// After [`run`](Self::run): writes each lane in use to `outp[at]` (`at`
    /// as pushed): its new F (if the model has one, `has_f`), `J`, `vc` and
    /// stress. Four lanes at a time through 4 × 4 transposes
    /// ([`V4::transpose`]): one store of four floats where a lane-by-lane
    /// copy makes four scalar stores, which made sand3d's g2p store-bound
    /// (docs/engine.md). Panics if an `at` is out of range.
    #[inline(always)]
    pub(crate) fn write_lanes<const D: usize>(
        &self,
        outp: &mut (impl ParticleSink<D> + ?Sized),
        has_f: bool,
    ) {
        let s = &self.s;
        let quads = self.len / 4 * 4;
        for l0 in (0..quads).step_by(4) {
            let at: [usize; 4] = std::array::from_fn(|q| self.at[l0 + q] as usize);
            if has_f {
                write_quad::<D, false>(outp, &at, &s.f, l0);
            }
            write_quad::<D, true>(outp, &at, &s.tau, l0);
            for (q, &a) in at.iter().enumerate() {
                let p = outp.at(a);
                (p.j, p.vc) = (s.j.0[l0 + q], s.vc.0[l0 + q]);
            }
        }
        for l in quads..self.len {
            let p = outp.at(self.at[l] as usize);
            for r in 0..D {
                for c in 0..D {
                    if has_f {
                        p.f[(r, c)] = s.f[r * D + c].0[l];
                    }
                    p.tau[(r, c)] = s.tau[r * D + c].0[l];
                }
            }
            (p.j, p.vc) = (s.j.0[l], s.vc.0[l]);
        }
    }

    /// Empties the batch (after its lanes were written).
    pub(crate) fn clear(&mut self) {
        self.len = 0;
    }
}

/// Lanes `l0 .. l0 + 4` of `src` (F, or τ if `TAU`) to the particles `at`,
/// through 4 × 4 transposes ([`Batch::write_lanes`]).
#[inline(always)]
fn write_quad<const D: usize, const TAU: bool>(
    outp: &mut (impl ParticleSink<D> + ?Sized),
    at: &[usize; 4],
    src: &[FL; 9],
    l0: usize,
) {
    let n = D * D;
    // batch index (row-major) of the particle's column-major entry `i`
    let comp = |i: usize| (i % D) * D + i / D;
    let mut i = 0;
    while i + 4 <= n {
        let rows: [V4; 4] = std::array::from_fn(|q| {
            let lanes: &[f32; 4] = src[comp(i + q)].0[l0..l0 + 4].try_into().unwrap();
            V4::load(lanes)
        });
        for (q, col) in V4::transpose(rows).into_iter().enumerate() {
            let p = outp.at(at[q]);
            let m = if TAU { &mut p.tau } else { &mut p.f };
            col.store(&mut m.as_mut_slice()[i..]);
        }
        i += 4;
    }
    for i in i..n {
        for (q, &a) in at.iter().enumerate() {
            let p = outp.at(a);
            let m = if TAU { &mut p.tau } else { &mut p.f };
            m.as_mut_slice()[i] = src[comp(i)].0[l0 + q];
        }
    }
}
