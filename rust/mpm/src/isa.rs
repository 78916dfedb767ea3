//! The instruction set the frame loop runs with, chosen at run time.
//!
//! The crate is built for the portable x86-64 baseline (SSE2), so the same
//! build runs on any x86-64 machine. The frame loop (`solver/frame.rs`: the
//! block sort, p2g, grid update, g2p and the material updates) is also
//! compiled a second time for x86-64-v3 (AVX2, FMA, BMI1/2, LZCNT, MOVBE,
//! F16C; Intel Haswell and AMD Excavator or later), and that copy runs when
//! the CPU has those features. It is the same source: the VEX encoding's
//! three-operand instructions and the BMI index arithmetic spare register
//! moves and spills of the SSE2 code (the stencil loops keep their 4-wide
//! lanes). A third copy for x86-64-v4 (AVX-512, 32 vector registers) was
//! measured no faster than v3 (docs/engine.md) and is not built.
//!
//! The two copies give **bitwise identical** results: Rust never contracts a
//! multiply and an add into a fused multiply-add on its own (FMA is only
//! used where the source asks for `mul_add`, which is correctly rounded on
//! either path), and every sum keeps its order. The tests step the same
//! scenes on both and compare the bits (`solver::frame::tests`).
//!
//! The material updates are compiled twice too, as their own functions
//! (`material::Batch::run`, one per model): each updates sixteen particles
//! of one parameter set at once in SIMD lanes, and the frame loop calls it
//! once per sixteen such particles.
//! The crate-private macro `x86_64_v3!` marks a function as the x86-64-v3 copy.
//!
//! The environment variable `HYBRIDMPM_ISA` (read when a solver is made, in
//! the vocabulary of `hybridmpm-isa` that every crate shares) caps the
//! choice: `baseline` forces the portable copy, e.g. to compare the two or to
//! rule the dispatch out while debugging; [`crate::Solver::set_isa`] does the
//! same for one solver. CPU detection is `hybridmpm-isa`'s too.

/// An instruction set the frame loop is compiled for.
/// Compiles the function it wraps for x86-64-v3 (on x86-64 only): the one
/// place the feature list is written. Calling it is `unsafe` except from
/// code compiled with the same features; call it only when
/// [`Isa::X86_64V3`] is [`available`](Isa::available).
macro_rules! x86_64_v3 {
    ($item:item) => {
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx,avx2,fma,bmi1,bmi2,lzcnt,movbe,f16c,popcnt")]
        $item
    };
}
pub(crate) use x86_64_v3;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Isa {
    /// The portable build (x86-64 baseline: SSE2; or the target's default
    /// elsewhere).
    Baseline,
    /// x86-64-v3: AVX2, FMA, BMI1/2, LZCNT, MOVBE, F16C.
    X86_64V3,
}

impl Isa {
    /// Every variant, the portable one first.
    pub const ALL: [Isa; 2] = [Isa::Baseline, Isa::X86_64V3];

    /// The name used by `HYBRIDMPM_ISA` and in reports: `"baseline"`, `"x86-64-v3"`.
    pub fn name(self) -> &'static str {
        match self {
            Isa::Baseline => "baseline",
            Isa::X86_64V3 => "x86-64-v3",
        }
    }

    /// The variant named `name` (see [`Isa::name`]).
    pub fn from_name(name: &str) -> Option<Isa> {
        Isa::ALL.into_iter().find(|i| i.name() == name.trim())
    }

    /// Whether this CPU can run the variant.
    pub fn available(self) -> bool {
        match self {
            Isa::Baseline => true,
            Isa::X86_64V3 => hybridmpm_isa::cpu::x86_64_v3(),
        }
    }

    /// The level of `hybridmpm-isa`'s vocabulary the variant needs.
    pub fn level(self) -> hybridmpm_isa::Level {
        match self {
            Isa::Baseline => hybridmpm_isa::Level::Baseline,
            Isa::X86_64V3 => hybridmpm_isa::Level::X86_64V3,
        }
    }

    /// The fastest variant this CPU runs within the ceiling `HYBRIDMPM_ISA`
    /// sets (an unknown name sets none: the choice never makes a solver fail).
    pub fn detect() -> Isa {
        Isa::ALL
            .into_iter()
            .rev()
            .find(|i| i.available() && i.level().allows())
            .unwrap_or(Isa::Baseline)
    }

    /// The fastest variant this CPU runs.
    pub fn best() -> Isa {
        Isa::ALL
            .into_iter()
            .rev()
            .find(|i| i.available())
            .unwrap_or(Isa::Baseline)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_the_baseline_is_always_there() {
        for isa in Isa::ALL {
            assert_eq!(Isa::from_name(isa.name()), Some(isa));
        }
        assert_eq!(Isa::from_name("avx9000"), None);
        for isa in Isa::ALL {
            assert_eq!(hybridmpm_isa::Level::parse(isa.name()), Some(isa.level()));
        }
        assert!(Isa::Baseline.available());
        assert!(Isa::best().available());
    }
}
