//! The instruction sets hybridmpm's compiled copies need, detected at run
//! time, and the one reading of `HYBRIDMPM_ISA` that every crate shares.
//!
//! The crates build for the portable x86-64 baseline and compile their hot
//! loops a second (and third) time behind `#[target_feature]`: the MPM frame
//! loop and sand update for x86-64-v3 (`hybridmpm-mpm`), the fused GNS kernels
//! for AVX2 + FMA and for AVX-512F (`hybridmpm-gnn`), the radius graph's
//! candidate compaction for AVX-512F + VL (`hybridmpm-neighbors`). Each crate
//! runs the fastest copy the CPU has ([`cpu`]) and that the environment
//! allows ([`Level::allows`]).
//!
//! # `HYBRIDMPM_ISA`
//!
//! The variable names the highest [`Level`] any crate may use, one vocabulary
//! for all of them: `baseline` (the portable code everywhere), `x86-64-v3`
//! (AVX2 at most: no AVX-512 copy runs) or `x86-64-v4` (everything the CPU
//! has, as when the variable is unset). `avx2` is accepted as another name
//! for `x86-64-v3`. An unknown value is ignored (the choice never makes a
//! solver fail). It is for comparisons and for ruling the dispatch out while
//! debugging: every copy gives the results its crate documents (the MPM
//! copies the same bits).
//!
//! Each crate reads the variable when it chooses (the MPM solver when it is
//! made, the GNS kernels per call, the radius graph once per process).

#![forbid(unsafe_code)]

/// The environment variable that caps the instruction set (module docs).
pub const ENV: &str = "HYBRIDMPM_ISA";

/// An x86-64 microarchitecture level, the ceiling `HYBRIDMPM_ISA` sets.
/// Ordered: `Baseline < X86_64V3 < X86_64V4`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Level {
    /// The portable build (x86-64 baseline: SSE2; or the target's default
    /// elsewhere).
    Baseline,
    /// x86-64-v3: AVX2, FMA, BMI1/2, LZCNT, MOVBE, F16C.
    X86_64V3,
    /// x86-64-v4: x86-64-v3 plus AVX-512.
    X86_64V4,
}

impl Level {
    /// Every level, lowest first.
    pub const ALL: [Level; 3] = [Level::Baseline, Level::X86_64V3, Level::X86_64V4];

    /// The level's name in `HYBRIDMPM_ISA` and in reports: `"baseline"`,
    /// `"x86-64-v3"`, `"x86-64-v4"`.
    pub fn name(self) -> &'static str {
        match self {
            Level::Baseline => "baseline",
            Level::X86_64V3 => "x86-64-v3",
            Level::X86_64V4 => "x86-64-v4",
        }
    }

    /// The level a value of `HYBRIDMPM_ISA` names: a [`name`](Level::name),
    /// or `avx2` for x86-64-v3; surrounding whitespace ignored. `None` for
    /// anything else.
    pub fn parse(value: &str) -> Option<Level> {
        match value.trim() {
            "avx2" => Some(Level::X86_64V3),
            v => Level::ALL.into_iter().find(|l| l.name() == v),
        }
    }

    /// The level `HYBRIDMPM_ISA` names now (read on every call), or `None`
    /// when it is unset or names none.
    pub fn requested() -> Option<Level> {
        std::env::var(ENV).ok().and_then(|v| Level::parse(&v))
    }

    /// The highest level the environment allows: [`Level::requested`], or
    /// x86-64-v4 (no cap) without one.
    pub fn ceiling() -> Level {
        Level::ceiling_of(std::env::var(ENV).ok().as_deref())
    }

    /// The ceiling a value of `HYBRIDMPM_ISA` sets (`None`: unset): the
    /// level it names, or x86-64-v4 (no cap) for none.
    pub fn ceiling_of(value: Option<&str>) -> Level {
        value.and_then(Level::parse).unwrap_or(Level::X86_64V4)
    }

    /// Whether the environment allows a copy that needs this level
    /// (`self ≤ `[`Level::ceiling`]).
    pub fn allows(self) -> bool {
        self <= Level::ceiling()
    }
}

/// What the CPU has, each check the feature set one kind of compiled copy
/// needs (false on other architectures).
pub mod cpu {
    /// x86-64-v3: AVX2, FMA, BMI1/2, LZCNT, MOVBE, F16C (the MPM frame loop's
    /// second copy).
    pub fn x86_64_v3() -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
                && std::arch::is_x86_feature_detected!("bmi1")
                && std::arch::is_x86_feature_detected!("bmi2")
                && std::arch::is_x86_feature_detected!("lzcnt")
                && std::arch::is_x86_feature_detected!("movbe")
                && std::arch::is_x86_feature_detected!("f16c")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    }

    /// AVX2 and FMA (the GNS kernels' AVX2 copies).
    pub fn avx2_fma() -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    }

    /// AVX-512F (the GNS kernels' AVX-512 copies).
    pub fn avx512f() -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            std::arch::is_x86_feature_detected!("avx512f")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    }

    /// AVX-512F and VL (the radius graph's AVX-512 compaction).
    pub fn avx512f_vl() -> bool {
        #[cfg(target_arch = "x86_64")]
        {
            std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("avx512vl")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_name_parses_back_to_its_level() {
        for level in Level::ALL {
            assert_eq!(Level::parse(level.name()), Some(level));
        }
    }

    #[test]
    fn the_old_spellings_keep_their_meaning() {
        // `avx2` capped the GNS kernels and the radius graph at AVX2: x86-64-v3
        assert_eq!(Level::parse("avx2"), Some(Level::X86_64V3));
        assert_eq!(Level::parse("baseline"), Some(Level::Baseline));
        assert_eq!(Level::parse("x86-64-v3"), Some(Level::X86_64V3));
    }

    #[test]
    fn whitespace_is_ignored_and_anything_else_names_no_level() {
        assert_eq!(Level::parse(" baseline\n"), Some(Level::Baseline));
        for v in ["", "avx512", "AVX2", "x86-64-v2", "x86-64", "native", "v3"] {
            assert_eq!(Level::parse(v), None, "{v:?}");
        }
    }

    #[test]
    fn an_unset_or_unknown_value_sets_no_cap() {
        assert_eq!(Level::ceiling_of(None), Level::X86_64V4);
        assert_eq!(Level::ceiling_of(Some("avx9000")), Level::X86_64V4);
        assert_eq!(Level::ceiling_of(Some("avx2")), Level::X86_64V3);
        assert_eq!(Level::ceiling_of(Some("baseline")), Level::Baseline);
        assert!(Level::Baseline.allows());
    }

    #[test]
    fn levels_are_ordered_lowest_first() {
        assert!(Level::Baseline < Level::X86_64V3 && Level::X86_64V3 < Level::X86_64V4);
        assert_eq!(Level::ALL.iter().min(), Some(&Level::Baseline));
    }

    #[test]
    fn the_cpu_checks_nest() {
        // a CPU with x86-64-v3 has AVX2 + FMA; AVX-512F + VL implies AVX-512F
        assert!(!cpu::x86_64_v3() || cpu::avx2_fma());
        assert!(!cpu::avx512f_vl() || cpu::avx512f());
    }
}
