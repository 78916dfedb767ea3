//! The few pieces of onnxruntime's C API (`onnxruntime_c_api.h`) the
//! operators use: the `OrtApi` entries by index, the status codes and
//! element types, `OrtApiBase`, and [`ort!`], `?` for an `OrtStatus*`.

use std::ffi::{c_char, c_int, c_void};
use std::sync::atomic::AtomicBool;

/// An `OrtStatus*`: null for success.
pub type Status = *mut c_void;
pub(crate) type Api = *const *const c_void;

/// `OrtApi` entries used (index in the table, `onnxruntime_c_api.h`).
pub(crate) mod idx {
    pub const CREATE_STATUS: usize = 0;
    pub const CREATE_CUSTOM_OP_DOMAIN: usize = 26;
    pub const CUSTOM_OP_DOMAIN_ADD: usize = 27;
    pub const ADD_CUSTOM_OP_DOMAIN: usize = 28;
    pub const GET_TENSOR_MUTABLE_DATA: usize = 51;
    pub const GET_TENSOR_ELEMENT_TYPE: usize = 60;
    pub const GET_DIMENSIONS_COUNT: usize = 61;
    pub const GET_DIMENSIONS: usize = 62;
    pub const GET_TENSOR_TYPE_AND_SHAPE: usize = 65;
    pub const KERNEL_CONTEXT_GET_INPUT: usize = 90;
    pub const KERNEL_CONTEXT_GET_OUTPUT: usize = 91;
    pub const RELEASE_STATUS: usize = 93;
    pub const RELEASE_TENSOR_TYPE_AND_SHAPE_INFO: usize = 99;
    /// Since `OrtApi` version 17 (asked for as [`super::PARALLEL_API_VERSION`]).
    pub const KERNEL_CONTEXT_PARALLEL_FOR: usize = 274;
}

/// The `OrtApi` version asked for: 16 (onnxruntime 1.16) has every entry
/// above but `KernelContext_ParallelFor`.
pub(crate) const API_VERSION: u32 = 16;
/// The version whose table has `KernelContext_ParallelFor` for certain
/// (onnxruntime 1.18, the oldest `pyproject.toml` allows): with an older
/// runtime the kernels run their parts on the calling thread.
pub(crate) const PARALLEL_API_VERSION: u32 = 18;
/// Whether the runtime that registered the operators has `KernelContext_ParallelFor`.
pub(crate) static HAS_PARALLEL_FOR: AtomicBool = AtomicBool::new(false);
pub(crate) const ORT_FAIL: c_int = 1;
pub(crate) const ORT_INVALID_ARGUMENT: c_int = 2;
pub(crate) const FLOAT: c_int = 1;
pub(crate) const INT64: c_int = 7;

/// `OrtApiBase`, the table onnxruntime hands to `RegisterCustomOps`.
#[repr(C)]
pub struct OrtApiBase {
    pub(crate) get_api: unsafe extern "C" fn(u32) -> Api,
    get_version_string: unsafe extern "C" fn() -> *const c_char,
}

pub(crate) unsafe fn api_fn<F: Copy>(api: Api, i: usize) -> F {
    // SAFETY: the caller names an index of `OrtApi` whose entry has type F.
    unsafe { std::mem::transmute_copy::<*const c_void, F>(&*api.add(i)) }
}

pub(crate) unsafe fn status(api: Api, code: c_int, msg: &str) -> Status {
    let text = std::ffi::CString::new(msg.replace('\0', " ")).unwrap_or_default();
    // SAFETY: CreateStatus(code, const char*) copies the message.
    unsafe {
        api_fn::<unsafe extern "C" fn(c_int, *const c_char) -> Status>(api, idx::CREATE_STATUS)(
            code,
            text.as_ptr(),
        )
    }
}

/// `?` for an `OrtStatus*`: non-null is an error to hand back.
macro_rules! ort {
    ($call:expr) => {{
        let s: Status = $call;
        if !s.is_null() {
            return Err(s);
        }
    }};
}

pub(crate) use ort;
