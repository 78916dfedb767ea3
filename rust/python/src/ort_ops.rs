//! The extension module is also onnxruntime's custom-op library for the
//! fused GNS kernels: `SessionOptions.register_custom_ops_library(
//! hybridmpm._core.__file__)` opens it and calls [`RegisterCustomOps`]. The
//! operators themselves (the C-ABI layer over `hybridmpm-gnn`) live in the
//! crate `hybridmpm-ort-ops` (`rust/ort-ops`); this is only the exported
//! symbol.

use std::ffi::c_void;

use hybridmpm_ort_ops::{OrtApiBase, Status, register_custom_ops};

/// The entry point onnxruntime calls when a session's options load this
/// library (`SessionOptions.register_custom_ops_library`).
///
/// # Safety
/// Called by onnxruntime with its session options and API base.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn RegisterCustomOps(
    options: *mut c_void,
    api_base: *const OrtApiBase,
) -> Status {
    // SAFETY: onnxruntime passes its `OrtSessionOptions` and `OrtApiBase`,
    // which is `register_custom_ops`'s contract.
    unsafe { register_custom_ops(options, api_base) }
}
