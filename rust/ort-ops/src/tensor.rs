//! The tensors onnxruntime hands a kernel: read with their shape and
//! element type checked, errors naming the argument.

use std::ffi::{c_int, c_void};

use crate::api::{Api, FLOAT, ORT_FAIL, ORT_INVALID_ARGUMENT, Status, api_fn, idx, ort, status};

/// A tensor onnxruntime handed over: its shape and data.
pub(crate) struct Tensor {
    pub(crate) dims: Vec<i64>,
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
    pub(crate) unsafe fn f32s<'a>(&self) -> &'a [f32] {
        if self.elements == 0 {
            &[]
        } else {
            unsafe { std::slice::from_raw_parts(self.data as *const f32, self.elements) }
        }
    }
    pub(crate) unsafe fn i64s<'a>(&self) -> &'a [i64] {
        if self.elements == 0 {
            &[]
        } else {
            unsafe { std::slice::from_raw_parts(self.data as *const i64, self.elements) }
        }
    }
    pub(crate) unsafe fn f32s_mut<'a>(&self) -> &'a mut [f32] {
        if self.elements == 0 {
            &mut []
        } else {
            unsafe { std::slice::from_raw_parts_mut(self.data as *mut f32, self.elements) }
        }
    }
}

pub(crate) unsafe fn input(
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

pub(crate) unsafe fn output(
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

pub(crate) fn first_dim(t: &Tensor) -> i64 {
    t.dims.first().copied().unwrap_or(0)
}
