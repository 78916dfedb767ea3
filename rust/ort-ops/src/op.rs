//! The operators as onnxruntime sees them: one `OrtCustomOp` per operator
//! (its name, input and output types), and the kernel it creates, whose
//! compute runs [`crate::compute::compute`] under `catch_unwind`.

use std::ffi::{c_char, c_int, c_void};
use std::panic::{AssertUnwindSafe, catch_unwind};

use crate::api::{Api, FLOAT, INT64, ORT_FAIL, Status, api_fn, idx, status};
use crate::compute::compute;
use crate::kernel::{Kernel, Which};

type Fp = Option<unsafe extern "C" fn()>;

/// `OrtCustomOp`, field for field (version 16 reads up to `kernel_compute_v2`).
#[repr(C)]
pub(crate) struct OrtCustomOp {
    version: u32,
    create_kernel:
        Option<unsafe extern "C" fn(*const OrtCustomOp, Api, *const c_void) -> *mut c_void>,
    get_name: Option<unsafe extern "C" fn(*const OrtCustomOp) -> *const c_char>,
    get_execution_provider_type: Option<unsafe extern "C" fn(*const OrtCustomOp) -> *const c_char>,
    get_input_type: Option<unsafe extern "C" fn(*const OrtCustomOp, usize) -> c_int>,
    get_input_type_count: Option<unsafe extern "C" fn(*const OrtCustomOp) -> usize>,
    get_output_type: Option<unsafe extern "C" fn(*const OrtCustomOp, usize) -> c_int>,
    get_output_type_count: Option<unsafe extern "C" fn(*const OrtCustomOp) -> usize>,
    kernel_compute: Option<unsafe extern "C" fn(*mut c_void, *mut c_void)>,
    kernel_destroy: Option<unsafe extern "C" fn(*mut c_void)>,
    get_input_characteristic: Option<unsafe extern "C" fn(*const OrtCustomOp, usize) -> c_int>,
    get_output_characteristic: Option<unsafe extern "C" fn(*const OrtCustomOp, usize) -> c_int>,
    get_input_memory_type: Option<unsafe extern "C" fn(*const OrtCustomOp, usize) -> c_int>,
    get_variadic_input_min_arity: Option<unsafe extern "C" fn(*const OrtCustomOp) -> c_int>,
    get_variadic_input_homogeneity: Option<unsafe extern "C" fn(*const OrtCustomOp) -> c_int>,
    get_variadic_output_min_arity: Option<unsafe extern "C" fn(*const OrtCustomOp) -> c_int>,
    get_variadic_output_homogeneity: Option<unsafe extern "C" fn(*const OrtCustomOp) -> c_int>,
    create_kernel_v2: Option<
        unsafe extern "C" fn(*const OrtCustomOp, Api, *const c_void, *mut *mut c_void) -> Status,
    >,
    kernel_compute_v2: Option<unsafe extern "C" fn(*mut c_void, *mut c_void) -> Status>,
    infer_output_shape: Fp,
    get_start_version: Fp,
    get_end_version: Fp,
    get_may_inplace: Fp,
    release_may_inplace: Fp,
    get_alias_map: Fp,
    release_alias_map: Fp,
}

/// One `OrtCustomOp` per operator; `which` recovers the operator from the
/// pointer onnxruntime passes back.
#[repr(C)]
pub(crate) struct Op {
    pub(crate) ort: OrtCustomOp,
    which: Which,
}

const fn op(which: Which) -> Op {
    Op {
        ort: OrtCustomOp {
            version: 16,
            create_kernel: Some(create_kernel),
            get_name: Some(get_name),
            get_execution_provider_type: Some(get_ep),
            get_input_type: Some(get_input_type),
            get_input_type_count: Some(get_input_type_count),
            get_output_type: Some(get_output_type),
            get_output_type_count: Some(get_output_type_count),
            kernel_compute: Some(kernel_compute),
            kernel_destroy: Some(kernel_destroy),
            get_input_characteristic: Some(required),
            get_output_characteristic: Some(required),
            get_input_memory_type: Some(default_memory),
            get_variadic_input_min_arity: Some(one),
            get_variadic_input_homogeneity: Some(one),
            get_variadic_output_min_arity: Some(one),
            get_variadic_output_homogeneity: Some(one),
            create_kernel_v2: Some(create_kernel_v2),
            kernel_compute_v2: Some(kernel_compute_v2),
            infer_output_shape: None,
            get_start_version: None,
            get_end_version: None,
            get_may_inplace: None,
            release_may_inplace: None,
            get_alias_map: None,
            release_alias_map: None,
        },
        which,
    }
}

pub(crate) static ENCODER: Op = op(Which::Encoder);
pub(crate) static BLOCK: Op = op(Which::Block);
pub(crate) static NODE: Op = op(Which::Node);
pub(crate) static NODE_ENCODER: Op = op(Which::NodeEncoder);
pub(crate) static DECODER: Op = op(Which::Decoder);

unsafe fn which(op: *const OrtCustomOp) -> Which {
    // SAFETY: onnxruntime passes back the pointer registered, the first field of an `Op`.
    unsafe { (*(op as *const Op)).which }
}

unsafe extern "C" fn get_name(op: *const OrtCustomOp) -> *const c_char {
    unsafe { which(op) }.name().as_ptr()
}

unsafe extern "C" fn get_ep(_: *const OrtCustomOp) -> *const c_char {
    c"CPUExecutionProvider".as_ptr()
}

fn input_types(w: Which) -> &'static [c_int] {
    match w {
        Which::Encoder => &[FLOAT; 10],
        Which::Block => &[
            FLOAT, FLOAT, FLOAT, INT64, INT64, FLOAT, FLOAT, FLOAT, FLOAT, FLOAT, FLOAT, FLOAT,
        ],
        Which::Node => &[FLOAT; 11],
        Which::NodeEncoder => &[
            FLOAT, INT64, FLOAT, FLOAT, FLOAT, FLOAT, FLOAT, FLOAT, FLOAT, FLOAT, FLOAT, FLOAT,
            FLOAT, FLOAT,
        ],
        Which::Decoder => &[
            FLOAT, FLOAT, INT64, INT64, FLOAT, FLOAT, FLOAT, FLOAT, FLOAT, FLOAT,
        ],
    }
}

fn output_count(w: Which) -> usize {
    match w {
        Which::Encoder | Which::Node | Which::NodeEncoder => 1,
        Which::Block | Which::Decoder => 2,
    }
}

unsafe extern "C" fn get_input_type(op: *const OrtCustomOp, i: usize) -> c_int {
    input_types(unsafe { which(op) })
        .get(i)
        .copied()
        .unwrap_or(0)
}

unsafe extern "C" fn get_input_type_count(op: *const OrtCustomOp) -> usize {
    input_types(unsafe { which(op) }).len()
}

unsafe extern "C" fn get_output_type(_: *const OrtCustomOp, _: usize) -> c_int {
    FLOAT
}

unsafe extern "C" fn get_output_type_count(op: *const OrtCustomOp) -> usize {
    output_count(unsafe { which(op) })
}

unsafe extern "C" fn required(_: *const OrtCustomOp, _: usize) -> c_int {
    0
}

unsafe extern "C" fn default_memory(_: *const OrtCustomOp, _: usize) -> c_int {
    0
}

unsafe extern "C" fn one(_: *const OrtCustomOp) -> c_int {
    1
}

unsafe extern "C" fn create_kernel(
    op: *const OrtCustomOp,
    api: Api,
    _: *const c_void,
) -> *mut c_void {
    Box::into_raw(Box::new(Kernel {
        api,
        which: unsafe { which(op) },
    })) as *mut c_void
}

unsafe extern "C" fn create_kernel_v2(
    op: *const OrtCustomOp,
    api: Api,
    info: *const c_void,
    out: *mut *mut c_void,
) -> Status {
    unsafe { *out = create_kernel(op, api, info) };
    std::ptr::null_mut()
}

unsafe extern "C" fn kernel_destroy(k: *mut c_void) {
    if !k.is_null() {
        drop(unsafe { Box::from_raw(k as *mut Kernel) });
    }
}

unsafe extern "C" fn kernel_compute(k: *mut c_void, ctx: *mut c_void) {
    let s = unsafe { kernel_compute_v2(k, ctx) };
    if !s.is_null() {
        let api = unsafe { (*(k as *const Kernel)).api };
        unsafe { api_fn::<unsafe extern "C" fn(Status)>(api, idx::RELEASE_STATUS)(s) };
    }
}

unsafe extern "C" fn kernel_compute_v2(k: *mut c_void, ctx: *mut c_void) -> Status {
    let kernel = unsafe { &*(k as *const Kernel) };
    let api = kernel.api;
    match catch_unwind(AssertUnwindSafe(|| unsafe { compute(kernel, ctx) })) {
        Ok(Ok(())) => std::ptr::null_mut(),
        Ok(Err(s)) => s,
        Err(_) => unsafe { status(api, ORT_FAIL, "hybridmpm.gnn kernel panicked") },
    }
}
