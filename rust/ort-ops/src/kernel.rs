//! What a kernel is, apart from how onnxruntime reaches it (`op.rs`) and
//! what it computes (`compute.rs`): the operator it runs and the API it
//! calls back.

use std::ffi::CStr;

use crate::api::Api;

/// Which operator a kernel computes.
#[derive(Clone, Copy, PartialEq, Eq)]
#[repr(u32)]
pub(crate) enum Which {
    Encoder,
    Block,
    Node,
    NodeEncoder,
    Decoder,
}

/// A kernel onnxruntime created: its operator and the API to answer through.
pub(crate) struct Kernel {
    pub(crate) api: Api,
    pub(crate) which: Which,
}

impl Which {
    /// The operator's name in the graph.
    pub(crate) fn name(self) -> &'static CStr {
        match self {
            Which::Encoder => c"HmpmEdgeEncoder",
            Which::Block => c"HmpmEdgeBlock",
            Which::Node => c"HmpmNodeBlock",
            Which::NodeEncoder => c"HmpmNodeEncoder",
            Which::Decoder => c"HmpmDecoder",
        }
    }
}
