//! onnxruntime custom operators for the fused GNS edge kernels
//! (`hybridmpm-gnn`): `HmpmEdgeEncoder`, `HmpmEdgeBlock`, `HmpmNodeBlock`,
//! `HmpmNodeEncoder` and `HmpmDecoder` in the domain
//! [`DOMAIN`], registered by [`register_custom_ops`].
//!
//! This crate is the C-ABI layer only; it needs neither Python nor
//! libpython. The extension module `hybridmpm._core` (`rust/python`) is the
//! custom-op library: it exports `RegisterCustomOps`, the entry point of
//! onnxruntime's C API for custom-op libraries (`onnxruntime_c_api.h`:
//! `OrtApiBase`, `OrtApi`, `OrtCustomOp`), as a one-line call of
//! [`register_custom_ops`], and onnxruntime's
//! `SessionOptions.register_custom_ops_library(hybridmpm._core.__file__)`
//! opens it and calls that entry point. The few `OrtApi` entries used are
//! called by their index in that table, which onnxruntime only ever appends
//! to; the operators declare `OrtCustomOp` version 16 (onnxruntime ≥ 1.16),
//! whose `KernelComputeV2` returns an error status instead of aborting.
//! Which graphs use the operators, and when: `hybridmpm.neural.fused`.
//!
//! Operator signatures (all float32 but the indices):
//!
//! * `HmpmEdgeEncoder(displacement [E, D], distance [E], w1 [D+1, 16], b1,
//!   w2 [16, 16], b2, w3 [16, 16], b3, kvar [16, 1], eps [1]) → [E, 16]`
//! * `HmpmEdgeBlock(e [E, 16], hr [N, 16], hs [N, 16], receivers int64 [E],
//!   senders int64 [E], we [16, 16], w2, b2, w3, b3, kvar, eps) →
//!   (e' [E, 16], agg [N, 16])`
//! * `HmpmNodeBlock(h [N, 16], agg [N, 16], degree [N, 1], w1 [33, 16], b1,
//!   w2, b2, w3, b3, kvar, eps) → h' [N, 16]`
//! * `HmpmNodeEncoder(positions [T, N, D], particle_type int64 [N], lower [D],
//!   upper [D], inv_w [], table [K, 16], w1 [(T-1)D+2D, 16], b1, w2, b2, w3,
//!   b3, kvar, eps) → h [N, 16]`
//! * `HmpmDecoder(h [N, 16], positions [T, N, D], particle_type int64 [N],
//!   kinematic int64 [], w1, b1, w2, b2, w3 [16, D], b3 [D]) →
//!   (acceleration [N, D], next_position [N, D])`
//!
//! Each kernel cuts its rows into fixed parts (`hybridmpm_gnn::PART_EDGES`,
//! `PART_NODES`) and runs them on the session's intra-op threads
//! (`KernelContext_ParallelFor`); the parts are fixed and each node's sum is
//! one part's, so the results are the same bits on any number of threads.
//!
//! Bad shapes or indices come back as an onnxruntime error naming the
//! argument (`INVALID_ARGUMENT`), never a crash: the kernel runs under
//! `catch_unwind`, and every pointer onnxruntime hands over is checked for
//! null before it is read.
//!
//! Modules: `api` (the C API's entries, codes and `OrtApiBase`), `op` (the
//! `OrtCustomOp` table of each operator and its kernel's life), `compute`
//! (a kernel's inputs, outputs and `hybridmpm-gnn` call), `tensor` (reading
//! a tensor onnxruntime hands over), `parallel` (the parts on onnxruntime's
//! intra-op threads); here the registration.

mod api;
mod compute;
mod kernel;
mod op;
mod parallel;
mod tensor;

use std::ffi::{CStr, c_char, c_void};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::atomic::{AtomicPtr, Ordering};

use api::{
    API_VERSION, Api, HAS_PARALLEL_FOR, ORT_FAIL, PARALLEL_API_VERSION, api_fn, idx, ort, status,
};
pub use api::{OrtApiBase, Status};
use op::{BLOCK, DECODER, ENCODER, NODE, NODE_ENCODER, OrtCustomOp};

/// The operators' domain in the ONNX graph.
pub const DOMAIN: &CStr = c"hybridmpm.gnn";

/// The domain, made once and kept for the life of the process (onnxruntime
/// needs it to outlive every session that uses it).
static DOMAIN_PTR: AtomicPtr<c_void> = AtomicPtr::new(std::ptr::null_mut());

unsafe fn register(options: *mut c_void, api: Api) -> Result<(), Status> {
    let mut domain = DOMAIN_PTR.load(Ordering::Acquire);
    if domain.is_null() {
        let mut d: *mut c_void = std::ptr::null_mut();
        type Create = unsafe extern "C" fn(*const c_char, *mut *mut c_void) -> Status;
        ort!(unsafe {
            api_fn::<Create>(api, idx::CREATE_CUSTOM_OP_DOMAIN)(DOMAIN.as_ptr(), &mut d)
        });
        type Add = unsafe extern "C" fn(*mut c_void, *const OrtCustomOp) -> Status;
        let add = unsafe { api_fn::<Add>(api, idx::CUSTOM_OP_DOMAIN_ADD) };
        ort!(unsafe { add(d, &ENCODER.ort) });
        ort!(unsafe { add(d, &BLOCK.ort) });
        ort!(unsafe { add(d, &NODE.ort) });
        ort!(unsafe { add(d, &NODE_ENCODER.ort) });
        ort!(unsafe { add(d, &DECODER.ort) });
        match DOMAIN_PTR.compare_exchange(
            std::ptr::null_mut(),
            d,
            Ordering::AcqRel,
            Ordering::Acquire,
        ) {
            Ok(_) => domain = d,
            Err(existing) => domain = existing, // another thread won; `d` is leaked (a few bytes, once)
        }
    }
    type AddDomain = unsafe extern "C" fn(*mut c_void, *mut c_void) -> Status;
    ort!(unsafe { api_fn::<AddDomain>(api, idx::ADD_CUSTOM_OP_DOMAIN)(options, domain) });
    Ok(())
}

/// What `RegisterCustomOps`, the entry point onnxruntime calls when a
/// session's options load the library
/// (`SessionOptions.register_custom_ops_library`), does: adds the domain
/// [`DOMAIN`] with the five operators to `options`. Returns null on success
/// (and when the runtime is too old to have API version 16, so the graph's
/// operators stay unknown), or an `OrtStatus` that onnxruntime owns.
///
/// # Safety
/// `options` must be onnxruntime's `OrtSessionOptions` and `api_base` its
/// `OrtApiBase`, as onnxruntime passes them to `RegisterCustomOps`.
pub unsafe fn register_custom_ops(options: *mut c_void, api_base: *const OrtApiBase) -> Status {
    if api_base.is_null() || options.is_null() {
        return std::ptr::null_mut();
    }
    let api = unsafe { ((*api_base).get_api)(API_VERSION) };
    if api.is_null() {
        return std::ptr::null_mut(); // too old a runtime: the graph's operators stay unknown and the session fails to load
    }
    let parallel = unsafe { ((*api_base).get_api)(PARALLEL_API_VERSION) };
    HAS_PARALLEL_FOR.store(!parallel.is_null(), Ordering::Release);
    match catch_unwind(AssertUnwindSafe(|| unsafe { register(options, api) })) {
        Ok(Ok(())) => std::ptr::null_mut(),
        Ok(Err(s)) => s,
        Err(_) => unsafe { status(api, ORT_FAIL, "hybridmpm.gnn: registration panicked") },
    }
}
