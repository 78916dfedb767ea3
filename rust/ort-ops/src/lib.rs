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

use std::ffi::{CStr, c_char, c_int, c_void};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::atomic::{AtomicBool, AtomicPtr, Ordering};

use hybridmpm_gnn::{
    KernelError, L, Mlp, ParallelFor, decoder, edge_block, edge_encoder, node_block, node_encoder,
};

/// The operators' domain in the ONNX graph.
pub const DOMAIN: &CStr = c"hybridmpm.gnn";

/// An `OrtStatus*`: null for success.
pub type Status = *mut c_void;
type Api = *const *const c_void;

/// `OrtApi` entries used (index in the table, `onnxruntime_c_api.h`).
mod idx {
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
const API_VERSION: u32 = 16;
/// The version whose table has `KernelContext_ParallelFor` for certain
/// (onnxruntime 1.18, the oldest `pyproject.toml` allows): with an older
/// runtime the kernels run their parts on the calling thread.
const PARALLEL_API_VERSION: u32 = 18;
/// Whether the runtime that registered the operators has `KernelContext_ParallelFor`.
static HAS_PARALLEL_FOR: AtomicBool = AtomicBool::new(false);
const ORT_FAIL: c_int = 1;
const ORT_INVALID_ARGUMENT: c_int = 2;
const FLOAT: c_int = 1;
const INT64: c_int = 7;

/// `OrtApiBase`, the table onnxruntime hands to `RegisterCustomOps`.
#[repr(C)]
pub struct OrtApiBase {
    get_api: unsafe extern "C" fn(u32) -> Api,
    get_version_string: unsafe extern "C" fn() -> *const c_char,
}

type Fp = Option<unsafe extern "C" fn()>;

/// `OrtCustomOp`, field for field (version 16 reads up to `kernel_compute_v2`).
#[repr(C)]
struct OrtCustomOp {
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

/// Which operator a kernel computes.
#[derive(Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
enum Which {
    Encoder,
    Block,
    Node,
    NodeEncoder,
    Decoder,
}

/// One `OrtCustomOp` per operator; `which` recovers the operator from the
/// pointer onnxruntime passes back.
#[repr(C)]
struct Op {
    ort: OrtCustomOp,
    which: Which,
}

struct Kernel {
    api: Api,
    which: Which,
}

unsafe fn api_fn<F: Copy>(api: Api, i: usize) -> F {
    // SAFETY: the caller names an index of `OrtApi` whose entry has type F.
    unsafe { std::mem::transmute_copy::<*const c_void, F>(&*api.add(i)) }
}

unsafe fn status(api: Api, code: c_int, msg: &str) -> Status {
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

static ENCODER: Op = op(Which::Encoder);
static BLOCK: Op = op(Which::Block);
static NODE: Op = op(Which::Node);
static NODE_ENCODER: Op = op(Which::NodeEncoder);
static DECODER: Op = op(Which::Decoder);

unsafe fn which(op: *const OrtCustomOp) -> Which {
    // SAFETY: onnxruntime passes back the pointer registered, the first field of an `Op`.
    unsafe { (*(op as *const Op)).which }
}

unsafe extern "C" fn get_name(op: *const OrtCustomOp) -> *const c_char {
    match unsafe { which(op) } {
        Which::Encoder => c"HmpmEdgeEncoder".as_ptr(),
        Which::Block => c"HmpmEdgeBlock".as_ptr(),
        Which::Node => c"HmpmNodeBlock".as_ptr(),
        Which::NodeEncoder => c"HmpmNodeEncoder".as_ptr(),
        Which::Decoder => c"HmpmDecoder".as_ptr(),
    }
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

/// A tensor onnxruntime handed over: its shape and data.
struct Tensor {
    dims: Vec<i64>,
    data: *mut c_void,
    elements: usize,
}

unsafe fn tensor(api: Api, value: *const c_void, name: &str, ty: c_int) -> Result<Tensor, Status> {
    if value.is_null() {
        return Err(unsafe { status(api, ORT_INVALID_ARGUMENT, &format!("{name}: missing")) });
    }
    let mut info: *mut c_void = std::ptr::null_mut();
    type TypeAndShape = unsafe extern "C" fn(*const c_void, *mut *mut c_void) -> Status;
    ort!(unsafe { api_fn::<TypeAndShape>(api, idx::GET_TENSOR_TYPE_AND_SHAPE)(value, &mut info) });
    let release = unsafe {
        api_fn::<unsafe extern "C" fn(*mut c_void)>(api, idx::RELEASE_TENSOR_TYPE_AND_SHAPE_INFO)
    };
    let read = || -> Result<(c_int, Vec<i64>), Status> {
        let mut t: c_int = 0;
        ort!(unsafe {
            api_fn::<unsafe extern "C" fn(*const c_void, *mut c_int) -> Status>(
                api,
                idx::GET_TENSOR_ELEMENT_TYPE,
            )(info, &mut t)
        });
        let mut n: usize = 0;
        ort!(unsafe {
            api_fn::<unsafe extern "C" fn(*const c_void, *mut usize) -> Status>(
                api,
                idx::GET_DIMENSIONS_COUNT,
            )(info, &mut n)
        });
        let mut dims = vec![0i64; n];
        ort!(unsafe {
            api_fn::<unsafe extern "C" fn(*const c_void, *mut i64, usize) -> Status>(
                api,
                idx::GET_DIMENSIONS,
            )(info, dims.as_mut_ptr(), n)
        });
        Ok((t, dims))
    };
    let got = read();
    unsafe { release(info) };
    let (t, dims) = got?;
    if t != ty {
        return Err(unsafe {
            status(
                api,
                ORT_INVALID_ARGUMENT,
                &format!("{name}: element type {t}, expected {ty}"),
            )
        });
    }
    let elements = dims.iter().try_fold(1usize, |a, &d| {
        usize::try_from(d).ok().and_then(|d| a.checked_mul(d))
    });
    let Some(elements) = elements else {
        return Err(unsafe {
            status(
                api,
                ORT_INVALID_ARGUMENT,
                &format!("{name}: bad shape {dims:?}"),
            )
        });
    };
    let mut data: *mut c_void = std::ptr::null_mut();
    ort!(unsafe {
        api_fn::<unsafe extern "C" fn(*const c_void, *mut *mut c_void) -> Status>(
            api,
            idx::GET_TENSOR_MUTABLE_DATA,
        )(value, &mut data)
    });
    if data.is_null() && elements > 0 {
        return Err(unsafe { status(api, ORT_FAIL, &format!("{name}: no data")) });
    }
    Ok(Tensor {
        dims,
        data,
        elements,
    })
}

impl Tensor {
    unsafe fn f32s<'a>(&self) -> &'a [f32] {
        if self.elements == 0 {
            &[]
        } else {
            unsafe { std::slice::from_raw_parts(self.data as *const f32, self.elements) }
        }
    }
    unsafe fn i64s<'a>(&self) -> &'a [i64] {
        if self.elements == 0 {
            &[]
        } else {
            unsafe { std::slice::from_raw_parts(self.data as *const i64, self.elements) }
        }
    }
    unsafe fn f32s_mut<'a>(&self) -> &'a mut [f32] {
        if self.elements == 0 {
            &mut []
        } else {
            unsafe { std::slice::from_raw_parts_mut(self.data as *mut f32, self.elements) }
        }
    }
}

unsafe fn input(
    api: Api,
    ctx: *mut c_void,
    i: usize,
    name: &str,
    ty: c_int,
) -> Result<Tensor, Status> {
    let mut v: *const c_void = std::ptr::null();
    type GetInput = unsafe extern "C" fn(*const c_void, usize, *mut *const c_void) -> Status;
    ort!(unsafe { api_fn::<GetInput>(api, idx::KERNEL_CONTEXT_GET_INPUT)(ctx, i, &mut v) });
    unsafe { tensor(api, v, name, ty) }
}

unsafe fn output(
    api: Api,
    ctx: *mut c_void,
    i: usize,
    name: &str,
    dims: &[i64],
) -> Result<Tensor, Status> {
    let mut v: *mut c_void = std::ptr::null_mut();
    type GetOutput =
        unsafe extern "C" fn(*mut c_void, usize, *const i64, usize, *mut *mut c_void) -> Status;
    ort!(unsafe {
        api_fn::<GetOutput>(api, idx::KERNEL_CONTEXT_GET_OUTPUT)(
            ctx,
            i,
            dims.as_ptr(),
            dims.len(),
            &mut v,
        )
    });
    unsafe { tensor(api, v, name, FLOAT) }
}

fn first_dim(t: &Tensor) -> i64 {
    t.dims.first().copied().unwrap_or(0)
}

/// The kernels' parts run by onnxruntime's intra-op thread pool
/// (`KernelContext_ParallelFor`): on as many threads as the session has
/// (one: the calling thread, in order). A part that panics on a worker is
/// caught there and re-raised on the calling thread, where
/// `kernel_compute_v2` turns it into an error status; if the runtime refuses
/// the call, the parts run on the calling thread (each part writes only its
/// own outputs, so running one again is harmless).
struct OrtParallel {
    api: Api,
    ctx: *mut c_void,
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

unsafe fn compute(k: &Kernel, ctx: *mut c_void) -> Result<(), Status> {
    let api = k.api;
    let par = OrtParallel { api, ctx };
    let fail = |e: KernelError| unsafe {
        status(
            api,
            ORT_INVALID_ARGUMENT,
            &format!("{:?}: {e}", k_name(k.which)),
        )
    };
    // the float inputs from `first` on, named for the error messages
    let floats = |first: usize, names: &[&str]| -> Result<Vec<Tensor>, Status> {
        names
            .iter()
            .enumerate()
            .map(|(j, n)| unsafe { input(api, ctx, first + j, n, FLOAT) })
            .collect()
    };
    match k.which {
        Which::Encoder => {
            let io = floats(0, &["displacement", "distance"])?;
            let (disp, dist) = (&io[0], &io[1]);
            let w = floats(2, &["w1", "b1", "w2", "b2", "w3", "b3", "kvar", "eps"])?;
            let dim = disp.dims.get(1).copied().unwrap_or(0).max(0) as usize;
            let out = unsafe { output(api, ctx, 0, "out", &[first_dim(dist), L as i64])? };
            let mlp = unsafe { mlp(&w[0], w[1].f32s(), &w[2..]) };
            edge_encoder(
                &mlp,
                dim,
                unsafe { disp.f32s() },
                unsafe { dist.f32s() },
                unsafe { out.f32s_mut() },
                &par,
            )
            .map_err(fail)
        }
        Which::Block => {
            let io = floats(0, &["e", "hr", "hs"])?;
            let (e, hr, hs) = (&io[0], &io[1], &io[2]);
            let recv = unsafe { input(api, ctx, 3, "receivers", INT64)? };
            let send = unsafe { input(api, ctx, 4, "senders", INT64)? };
            let w = floats(5, &["we", "w2", "b2", "w3", "b3", "kvar", "eps"])?;
            let out = unsafe { output(api, ctx, 0, "e_out", &[first_dim(&recv), L as i64])? };
            let agg = unsafe { output(api, ctx, 1, "agg", &[first_dim(hr), L as i64])? };
            let zeros = [0.0f32; L]; // the first layer's bias is inside `hr`
            let mlp = unsafe { mlp(&w[0], &zeros, &w[1..]) };
            edge_block(
                &mlp,
                unsafe { e.f32s() },
                unsafe { hr.f32s() },
                unsafe { hs.f32s() },
                unsafe { recv.i64s() },
                unsafe { send.i64s() },
                unsafe { out.f32s_mut() },
                unsafe { agg.f32s_mut() },
                &par,
            )
            .map_err(fail)
        }
        Which::NodeEncoder => {
            let pos = unsafe { input(api, ctx, 0, "positions", FLOAT)? };
            let ptype = unsafe { input(api, ctx, 1, "particle_type", INT64)? };
            let geo = floats(2, &["lower", "upper", "inv_w", "table"])?;
            let w = floats(6, &["w1", "b1", "w2", "b2", "w3", "b3", "kvar", "eps"])?;
            let dim = pos.dims.get(2).copied().unwrap_or(0).max(0) as usize;
            let out = unsafe { output(api, ctx, 0, "h", &[first_dim(&ptype), L as i64])? };
            let mlp = unsafe { mlp(&w[0], w[1].f32s(), &w[2..]) };
            let inv_w = unsafe { geo[2].f32s() }
                .first()
                .copied()
                .unwrap_or(f32::NAN);
            node_encoder(
                &mlp,
                dim,
                unsafe { pos.f32s() },
                unsafe { ptype.i64s() },
                unsafe { geo[0].f32s() },
                unsafe { geo[1].f32s() },
                inv_w,
                unsafe { geo[3].f32s() },
                unsafe { out.f32s_mut() },
                &par,
            )
            .map_err(fail)
        }
        Which::Decoder => {
            let io = floats(0, &["h", "positions"])?;
            let ptype = unsafe { input(api, ctx, 2, "particle_type", INT64)? };
            let kin = unsafe { input(api, ctx, 3, "kinematic", INT64)? };
            let w = floats(4, &["w1", "b1", "w2", "b2", "w3", "b3"])?;
            let dim = io[1].dims.get(2).copied().unwrap_or(0).max(0);
            let n = first_dim(&ptype);
            let acc = unsafe { output(api, ctx, 0, "acceleration", &[n, dim])? };
            let next = unsafe { output(api, ctx, 1, "next_position", &[n, dim])? };
            let Some(&kinematic) = (unsafe { kin.i64s() }).first() else {
                return Err(unsafe {
                    status(api, ORT_INVALID_ARGUMENT, "HmpmDecoder: kinematic: missing")
                });
            };
            let mlp = unsafe {
                Mlp {
                    w1: w[0].f32s(),
                    b1: w[1].f32s(),
                    w2: w[2].f32s(),
                    b2: w[3].f32s(),
                    w3: w[4].f32s(),
                    b3: w[5].f32s(),
                    kvar: &[],
                    eps: f32::NAN,
                }
            };
            decoder(
                &mlp,
                dim as usize,
                unsafe { io[0].f32s() },
                unsafe { io[1].f32s() },
                unsafe { ptype.i64s() },
                kinematic,
                unsafe { acc.f32s_mut() },
                unsafe { next.f32s_mut() },
                &par,
            )
            .map_err(fail)
        }
        Which::Node => {
            let io = floats(0, &["h", "agg", "degree"])?;
            let w = floats(3, &["w1", "b1", "w2", "b2", "w3", "b3", "kvar", "eps"])?;
            let out = unsafe { output(api, ctx, 0, "h_out", &[first_dim(&io[2]), L as i64])? };
            let mlp = unsafe { mlp(&w[0], w[1].f32s(), &w[2..]) };
            node_block(
                &mlp,
                unsafe { io[0].f32s() },
                unsafe { io[1].f32s() },
                unsafe { io[2].f32s() },
                unsafe { out.f32s_mut() },
                &par,
            )
            .map_err(fail)
        }
    }
}

fn k_name(w: Which) -> &'static str {
    match w {
        Which::Encoder => "HmpmEdgeEncoder",
        Which::Block => "HmpmEdgeBlock",
        Which::Node => "HmpmNodeBlock",
        Which::NodeEncoder => "HmpmNodeEncoder",
        Which::Decoder => "HmpmDecoder",
    }
}

/// The MLP of the first layer `w1`, its bias `b1` and the rest
/// `[w2, b2, w3, b3, kvar, eps]` as onnxruntime handed them over.
unsafe fn mlp<'a>(w1: &'a Tensor, b1: &'a [f32], rest: &'a [Tensor]) -> Mlp<'a> {
    unsafe {
        Mlp {
            w1: w1.f32s(),
            b1,
            w2: rest[0].f32s(),
            b2: rest[1].f32s(),
            w3: rest[2].f32s(),
            b3: rest[3].f32s(),
            kvar: rest[4].f32s(),
            eps: rest[5].f32s().first().copied().unwrap_or(f32::NAN),
        }
    }
}

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
