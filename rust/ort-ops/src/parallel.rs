//! [`OrtParallel`]: the kernels' fixed parts on onnxruntime's intra-op
//! threads (`KernelContext_ParallelFor`).

use std::ffi::c_void;
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::atomic::{AtomicBool, Ordering};

use hybridmpm_gnn::ParallelFor;

use crate::api::{Api, HAS_PARALLEL_FOR, Status, api_fn, idx};

/// The kernels' parts run by onnxruntime's intra-op thread pool
/// (`KernelContext_ParallelFor`): on as many threads as the session has
/// (one: the calling thread, in order). A part that panics on a worker is
/// caught there and re-raised on the calling thread, where
/// `kernel_compute_v2` turns it into an error status; if the runtime refuses
/// the call, the parts run on the calling thread (each part writes only its
/// own outputs, so running one again is harmless).
pub(crate) struct OrtParallel {
    pub(crate) api: Api,
    pub(crate) ctx: *mut c_void,
}

struct PartsCall<'a> {
    f: &'a (dyn Fn(usize) + Sync),
    panicked: AtomicBool,
}

unsafe extern "C" fn run_part(data: *mut c_void, i: usize) {
    // SAFETY: `data` is the `PartsCall` that `OrtParallel::run` keeps alive until the call returns.
    let call = unsafe { &*(data as *const PartsCall<'_>) };
    if catch_unwind(AssertUnwindSafe(|| (call.f)(i))).is_err() {
        call.panicked.store(true, Ordering::Release);
    }
}

impl ParallelFor for OrtParallel {
    fn run(&self, n: usize, f: &(dyn Fn(usize) + Sync)) {
        if n <= 1 || !HAS_PARALLEL_FOR.load(Ordering::Acquire) {
            return (0..n).for_each(f);
        }
        let call = PartsCall {
            f,
            panicked: AtomicBool::new(false),
        };
        type Par = unsafe extern "C" fn(
            *const c_void,
            unsafe extern "C" fn(*mut c_void, usize),
            usize,
            usize,
            *mut c_void,
        ) -> Status;
        // SAFETY: entry 274 of a table of version >= 18 (checked at registration) is
        // KernelContext_ParallelFor; `ctx` is the running kernel's context; it returns
        // after every part has run.
        let s = unsafe {
            api_fn::<Par>(self.api, idx::KERNEL_CONTEXT_PARALLEL_FOR)(
                self.ctx,
                run_part,
                n,
                0,
                &call as *const PartsCall<'_> as *mut c_void,
            )
        };
        if !s.is_null() {
            unsafe { api_fn::<unsafe extern "C" fn(Status)>(self.api, idx::RELEASE_STATUS)(s) };
            return (0..n).for_each(f);
        }
        if call.panicked.load(Ordering::Acquire) {
            panic!("a part of the kernel panicked on an onnxruntime worker");
        }
    }
}
