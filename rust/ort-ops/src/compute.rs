//! A kernel's compute: its inputs read and checked by name, its outputs
//! allocated, and the `hybridmpm-gnn` kernel run on them.

use std::ffi::c_void;

use hybridmpm_gnn::{
    KernelError, L, Mlp, decoder, edge_block, edge_encoder, node_block, node_encoder,
};

use crate::api::{FLOAT, INT64, ORT_INVALID_ARGUMENT, Status, status};
use crate::kernel::{Kernel, Which};
use crate::parallel::OrtParallel;
use crate::tensor::{Tensor, first_dim, input, output};

pub(crate) unsafe fn compute(k: &Kernel, ctx: *mut c_void) -> Result<(), Status> {
    let api = k.api;
    let par = OrtParallel { api, ctx };
    let fail = |e: KernelError| unsafe {
        status(
            api,
            ORT_INVALID_ARGUMENT,
            &format!("{:?}: {e}", k.which.name()),
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
