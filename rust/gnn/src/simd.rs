//! A latent row in registers, one implementation per instruction set
//! ([`Lanes`]), and the choice of the copy this CPU runs ([`Isa`]).

use crate::{L, Row};

/// A latent row in registers and the few operations the kernels need. One
/// implementation per instruction set; the kernels (`crate::kernels`) are
/// written once, over this trait, and compiled into each copy (the copy's
/// function enables the target features, and everything here is inlined into
/// it).
///
/// # Safety
/// The methods may use the instruction set of their implementation: call
/// them only from a function compiled with it, on a CPU that has it. `load`
/// and `store` need slices of at least [`L`] values.
pub(crate) unsafe trait Lanes {
    /// A row of [`L`] values.
    type R: Copy;
    unsafe fn zero() -> Self::R;
    unsafe fn load(p: &[f32]) -> Self::R;
    unsafe fn store(p: &mut [f32], r: Self::R);
    unsafe fn add(a: Self::R, b: Self::R) -> Self::R;
    unsafe fn relu(a: Self::R) -> Self::R;
    /// `acc + x · w` (every lane of `w` times the scalar `x`).
    unsafe fn madd(x: f32, w: Self::R, acc: Self::R) -> Self::R;
    /// The folded LayerNorm of `o`: `o / sqrt(Σ_j k_j o_j² + eps)`.
    unsafe fn norm(o: Self::R, k: Self::R, eps: f32) -> Self::R;
}

/// Plain Rust, no FMA: the copy for any CPU.
pub(crate) struct Portable;

// SAFETY: plain Rust; `load` and `store` index the first L values (checked).
unsafe impl Lanes for Portable {
    type R = Row;
    #[inline(always)]
    unsafe fn zero() -> Row {
        [0.0; L]
    }
    #[inline(always)]
    unsafe fn load(p: &[f32]) -> Row {
        p[..L].try_into().expect("a row of L values")
    }
    #[inline(always)]
    unsafe fn store(p: &mut [f32], r: Row) {
        p[..L].copy_from_slice(&r);
    }
    #[inline(always)]
    unsafe fn add(a: Row, b: Row) -> Row {
        std::array::from_fn(|j| a[j] + b[j])
    }
    #[inline(always)]
    unsafe fn relu(a: Row) -> Row {
        a.map(|v| v.max(0.0))
    }
    #[inline(always)]
    unsafe fn madd(x: f32, w: Row, acc: Row) -> Row {
        std::array::from_fn(|j| x * w[j] + acc[j])
    }
    #[inline(always)]
    unsafe fn norm(o: Row, k: Row, eps: f32) -> Row {
        let var: f32 = (0..L).map(|j| o[j] * o[j] * k[j]).sum();
        let std = (var + eps).sqrt();
        o.map(|v| v / std)
    }
}

/// AVX2 + FMA: a row is two 8-lane registers.
#[cfg(target_arch = "x86_64")]
pub(crate) struct Avx2;

#[cfg(target_arch = "x86_64")]
// SAFETY: AVX/AVX2/FMA intrinsics, used only inside `#[target_feature(enable = "avx,avx2,fma")]` copies; rows of L values.
unsafe impl Lanes for Avx2 {
    type R = (std::arch::x86_64::__m256, std::arch::x86_64::__m256);
    #[inline(always)]
    unsafe fn zero() -> Self::R {
        use std::arch::x86_64::*;
        unsafe { (_mm256_setzero_ps(), _mm256_setzero_ps()) }
    }
    #[inline(always)]
    unsafe fn load(p: &[f32]) -> Self::R {
        use std::arch::x86_64::*;
        assert!(p.len() >= L);
        unsafe {
            (
                _mm256_loadu_ps(p.as_ptr()),
                _mm256_loadu_ps(p.as_ptr().add(8)),
            )
        }
    }
    #[inline(always)]
    unsafe fn store(p: &mut [f32], r: Self::R) {
        use std::arch::x86_64::*;
        assert!(p.len() >= L);
        unsafe {
            _mm256_storeu_ps(p.as_mut_ptr(), r.0);
            _mm256_storeu_ps(p.as_mut_ptr().add(8), r.1);
        }
    }
    #[inline(always)]
    unsafe fn add(a: Self::R, b: Self::R) -> Self::R {
        use std::arch::x86_64::*;
        unsafe { (_mm256_add_ps(a.0, b.0), _mm256_add_ps(a.1, b.1)) }
    }
    #[inline(always)]
    unsafe fn relu(a: Self::R) -> Self::R {
        use std::arch::x86_64::*;
        unsafe {
            let z = _mm256_setzero_ps();
            (_mm256_max_ps(a.0, z), _mm256_max_ps(a.1, z))
        }
    }
    #[inline(always)]
    unsafe fn madd(x: f32, w: Self::R, acc: Self::R) -> Self::R {
        use std::arch::x86_64::*;
        unsafe {
            let b = _mm256_set1_ps(x);
            (
                _mm256_fmadd_ps(b, w.0, acc.0),
                _mm256_fmadd_ps(b, w.1, acc.1),
            )
        }
    }
    #[inline(always)]
    unsafe fn norm(o: Self::R, k: Self::R, eps: f32) -> Self::R {
        use std::arch::x86_64::*;
        unsafe {
            let s = _mm256_fmadd_ps(
                _mm256_mul_ps(o.0, o.0),
                k.0,
                _mm256_mul_ps(_mm256_mul_ps(o.1, o.1), k.1),
            );
            let h = _mm_add_ps(_mm256_castps256_ps128(s), _mm256_extractf128_ps(s, 1));
            let h = _mm_add_ps(h, _mm_movehl_ps(h, h));
            let h = _mm_add_ss(h, _mm_shuffle_ps(h, h, 1));
            let d = _mm256_broadcastss_ps(_mm_sqrt_ss(_mm_add_ss(h, _mm_set_ss(eps))));
            (_mm256_div_ps(o.0, d), _mm256_div_ps(o.1, d))
        }
    }
}

/// AVX-512F: a row is one 16-lane register.
#[cfg(target_arch = "x86_64")]
pub(crate) struct Avx512;

#[cfg(target_arch = "x86_64")]
// SAFETY: AVX-512F intrinsics, used only inside `#[target_feature(enable = "avx512f")]` copies; rows of L values.
unsafe impl Lanes for Avx512 {
    type R = std::arch::x86_64::__m512;
    #[inline(always)]
    unsafe fn zero() -> Self::R {
        unsafe { std::arch::x86_64::_mm512_setzero_ps() }
    }
    #[inline(always)]
    unsafe fn load(p: &[f32]) -> Self::R {
        assert!(p.len() >= L);
        unsafe { std::arch::x86_64::_mm512_loadu_ps(p.as_ptr()) }
    }
    #[inline(always)]
    unsafe fn store(p: &mut [f32], r: Self::R) {
        assert!(p.len() >= L);
        unsafe { std::arch::x86_64::_mm512_storeu_ps(p.as_mut_ptr(), r) }
    }
    #[inline(always)]
    unsafe fn add(a: Self::R, b: Self::R) -> Self::R {
        unsafe { std::arch::x86_64::_mm512_add_ps(a, b) }
    }
    #[inline(always)]
    unsafe fn relu(a: Self::R) -> Self::R {
        use std::arch::x86_64::*;
        unsafe { _mm512_max_ps(a, _mm512_setzero_ps()) }
    }
    #[inline(always)]
    unsafe fn madd(x: f32, w: Self::R, acc: Self::R) -> Self::R {
        use std::arch::x86_64::*;
        unsafe { _mm512_fmadd_ps(_mm512_set1_ps(x), w, acc) }
    }
    #[inline(always)]
    unsafe fn norm(o: Self::R, k: Self::R, eps: f32) -> Self::R {
        use std::arch::x86_64::*;
        unsafe {
            let var = _mm512_reduce_add_ps(_mm512_mul_ps(_mm512_mul_ps(o, o), k));
            _mm512_div_ps(o, _mm512_set1_ps((var + eps).sqrt()))
        }
    }
}

/// The instruction set the kernels run with, chosen once per call from the
/// CPU and the ceiling `HYBRIDMPM_ISA` sets (`hybridmpm-isa`'s vocabulary:
/// `baseline` forces the portable copy, `x86-64-v3` or `avx2` the AVX2 one
/// at most: for comparisons).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Isa {
    /// Plain Rust, no FMA.
    Portable,
    /// AVX2 + FMA, two 8-lane registers per latent row.
    Avx2,
    /// AVX-512F, one 16-lane register per latent row.
    Avx512,
}

/// The copy this CPU runs (see [`Isa`]).
pub fn isa() -> Isa {
    use hybridmpm_isa::{Level, cpu};
    let ceiling = Level::ceiling();
    if ceiling >= Level::X86_64V4 && cpu::avx512f() {
        Isa::Avx512
    } else if ceiling >= Level::X86_64V3 && cpu::avx2_fma() {
        Isa::Avx2
    } else {
        Isa::Portable
    }
}

/// Whether this CPU runs a copy with fused multiply-adds.
pub fn uses_fma() -> bool {
    isa() != Isa::Portable
}
