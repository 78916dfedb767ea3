"""The inference graph of a trained GNS, written op by op for onnxruntime's CPU
kernels (paper App. A; GNS, Sanchez-Gonzalez et al. 2020).

:func:`inference_graph` turns the weights of a
:class:`~hybridmpm.train.gns.model.GnsModel` into an ONNX graph that computes the
same function as ``GnsModel.forward`` (float32 rounding aside; the tests check
it against torch) with fewer and cheaper passes over the ``E × latent`` edge
arrays. On this class of machine every operator over an edge array costs
8–22 ns per edge whatever it computes, and onnxruntime's
``LayerNormalization`` 53–74 ns per row of 16 (``benchmarks/bench_inference.py
--ops``), so the graph is shaped by counting passes, not FLOPs:

* **Edge geometry from the radius-graph pass.** The Rust cell list already
  returns ``p_s − p_r`` and its norm (:func:`hybridmpm.graph.radius_graph`);
  the graph takes them as inputs (``displacement`` [E, D], ``distance`` [E],
  metres) instead of gathering positions, and ``1/R`` is folded into the
  edge encoder's first layer.
* **Normalisations folded into weights.** The velocity statistics
  (``(v − mean)/std``) into the node encoder's first layer, the type
  embedding into a per-type table of that layer's output, the output
  statistics (``a·std + mean``) into the decoder's last layer.
* **LayerNorm folded into the Linear before it.** ``LN(z) = g ⊙ (z − z̄)/σ + β``
  with ``z = xW + b``: centring is linear, ``z − z̄ = x W C + b C`` with
  ``C = I − 11ᵀ/L``, and the gain scales columns, so one Gemm with
  ``W C diag(g)`` gives ``d_g = g ⊙ (z − z̄)``; ``σ²`` is then
  ``(d_g ⊙ d_g) · (1/g²)/L`` plus ``ε`` (one Gemm to a single column), and
  the output is ``d_g / sqrt(σ² + ε)``, the square root taken on that column
  and widened by a MatMul with a row of ones (``1ᵀ``) so that the division
  is between equal shapes: 5 cheap passes instead of one slow kernel. (A
  variance as wide as the latent, a MatMul with ``diag(1/g²) 11ᵀ/L`` with the
  ``Add`` of ``ε`` and the ``Sqrt`` on all of it, costs 12.6 against 8.0 ns
  per row of 16, ``benchmarks/bench_inference.py --ops``; dividing by the
  column itself, onnxruntime's broadcasting ``Div``, 11.8.)
  (A gain with an entry of magnitude below :data:`MIN_GAIN` is applied by a
  MatMul after the division instead.)
* **Carried biases.** The LayerNorm's ``β`` is not added: a latent is kept
  as a tensor plus a constant row ``c`` (the sum of the ``β`` of the residual
  updates so far), and every Linear that reads it folds ``c W`` into its
  bias; a sum over ``k`` edges of such latents carries ``k·c``, added through
  the receiver degree as one more input column of the node MLP. No broadcast
  bias add (25–37 ns per row here) is left on an edge array.
* **Gather, not GatherND**, for the per-edge node projections of the
  factored first edge layer (``(W_r h)[r] + (W_s h)[s]``).
* **The sum over receivers, two ways** (:func:`_aggregate`, an ``If`` on the
  width of ``in_edges``). onnxruntime's CPU ``ScatterND`` with
  ``reduction="add"`` splits the edges among its threads and adds without
  atomics, so on more than one thread two edges into one node can be added at
  once and one of them lost (microsoft/onnxruntime#23396; here, on edges in a
  random order, 300 runs of 300 came out wrong on 2 threads, and on edges
  sorted by receiver, where only the edges of a node split between two
  threads' ranges can collide, a CI run lost one). So: with ``in_edges`` of
  width 0 the sum is that ``ScatterND`` (exact on one thread, and the cheaper);
  with ``in_edges`` [N, K] (each node's in-edges, padded with index E:
  :func:`hybridmpm.neural.runtime.aggregation_inputs`) it is a ``Gather`` of
  the edge rows and one zero row appended at index E to [N, K, latent] and a
  ``ReduceSum`` over K: no two threads write one row, on any thread count,
  and the padding adds exact zeros. (Padding with a real edge and taking
  ``(K − deg)·e`` off again cancelled badly when a few nodes have very many
  in-edges: 4.6e-2 relative on the others with one node of 4 000.) The
  receiver degree is an input (``in_degree``), not a third sum.

Inputs (names :data:`INPUT_NAMES`): ``positions`` float32 [t_in, N, D] (m,
oldest first), ``particle_type`` int64 [N], ``senders``, ``receivers`` int64
[E], ``displacement`` float32 [E, D] (``p_s − p_r`` of ``positions[-1]``, m),
``distance`` float32 [E] (its norm, m), ``in_edges`` int64 [N, K] (K may be
0) and ``in_degree`` float32 [N, 1] (edges into each node).
Outputs (:data:`OUTPUT_NAMES`):
``acceleration`` [N, D] (m/step²) and ``next_position`` [N, D] (m), kinematic
particles kept in place. Needs ``onnx`` (the 'train' extra); running the
graph needs only onnxruntime.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from hybridmpm.conventions import GNS_KINEMATIC
from hybridmpm.neural.constants import CONTEXT_INPUT, GRAPH_LAYOUT, INPUT_NAMES, METADATA_KEY, OUTPUT_NAMES
from hybridmpm.train.gns.model import LN_EPS, remap_legacy_state_dict

#: ONNX opset of the graph.
OPSET = 18
#: Node-name prefixes of the graph's stages, in execution order.
STAGES = ("features", "node_encoder", "edge_encoder", "edge_mlp", "aggregate", "node_mlp", "decoder")
#: LayerNorm gains smaller than this (in magnitude) are applied after the division, not folded.
MIN_GAIN = 1e-4


class _Builder:
    """A list of ONNX nodes and initializers with fresh names."""

    def __init__(self) -> None:
        self.nodes: list[Any] = []
        self.inits: list[Any] = []
        self._n = 0
        #: Prefix of the node names (``stage/op_n``): onnxruntime's profiler reports
        #: per node, and ``benchmarks/bench_inference.py`` groups by it (:data:`STAGES`).
        self.stage = "features"

    def name(self, hint: str) -> str:
        self._n += 1
        return f"{hint}_{self._n}"

    def const(self, hint: str, value: Any, dtype: Any = np.float32) -> str:
        from onnx import numpy_helper

        name = self.name(hint)
        self.inits.append(numpy_helper.from_array(np.asarray(value, dtype=dtype), name))
        return name

    def op(self, op_type: str, inputs: list[str], hint: str | None = None, **attrs: Any) -> str:
        from onnx import helper

        out = self.name(hint or op_type.lower())
        self.nodes.append(helper.make_node(op_type, inputs, [out], name=f"{self.stage}/{out}", **attrs))
        return out


#: A latent as a tensor name plus a constant row added to every row (None: zero).
Latent = tuple[str, "np.ndarray | None"]


def _t(w: Any) -> np.ndarray:
    """A torch Linear weight [out, in] as the float64 matrix of ``x @ W`` [in, out]."""
    return np.asarray(w, np.float64).T.copy()


def _vec(v: Any) -> np.ndarray:
    return np.asarray(v, np.float64).reshape(-1)


class _Compiler:
    def __init__(self, sd: Mapping[str, np.ndarray], eps: float) -> None:
        self.sd = sd
        self.eps = eps
        self.b = _Builder()

    def w(self, key: str) -> np.ndarray:
        return _t(self.sd[key + ".weight"])

    def bias(self, key: str) -> np.ndarray:
        return _vec(self.sd[key + ".bias"])

    # --------------------------------------------------------------- layers
    def gemm(self, x: str, w: np.ndarray, bias: np.ndarray, relu: bool = False) -> str:
        """``x @ w + bias`` (ReLU after it if asked: onnxruntime fuses Gemm + Relu)."""
        b = self.b
        out = b.op("Gemm", [x, b.const("W", w), b.const("b", bias)], "gemm")
        return b.op("Relu", [out], "relu") if relu else out

    def linear_in(self, xs: list[tuple[Latent, np.ndarray]], bias: np.ndarray) -> tuple[list[tuple[str, np.ndarray]], np.ndarray]:
        """Fold the carried constants of ``xs`` into ``bias``: returns the (tensor, W) terms and the new bias."""
        total = bias.copy()
        terms = []
        for (name, c), w in xs:
            if c is not None:
                total = total + c @ w
            terms.append((name, w))
        return terms, total

    def layer_norm_linear(self, x: str, w: np.ndarray, bias: np.ndarray, ln: str) -> Latent:
        """``LayerNorm(x @ w + bias)`` of the state-dict LayerNorm ``ln`` as ``(d / σ, β)`` (module doc)."""
        b = self.b
        g, beta = _vec(self.sd[ln + ".weight"]), _vec(self.sd[ln + ".bias"])
        width = len(g)
        centre = np.eye(width) - np.full((width, width), 1.0 / width)
        fold = bool(np.all(np.abs(g) >= MIN_GAIN))
        scale = np.diag(g) if fold else np.eye(width)
        d = self.gemm(x, w @ centre @ scale, bias @ centre @ scale)
        inv_g2 = 1.0 / (g * g) if fold else np.ones(width)
        y = b.op("Div", [d, _layer_norm_scale(b, b.op("Mul", [d, d], "sq"), inv_g2 / width, self.eps)], "ln")
        if not fold:
            y = b.op("MatMul", [y, b.const("G", np.diag(g))], "ln_g")
        return y, beta

    def mlp(self, terms: list[tuple[str, np.ndarray]], bias0: np.ndarray, key: str, layer_norm: bool, extra: str | None = None) -> Latent:
        """The state-dict MLP ``key`` (Linear 0, 2, 4 with ReLU; LayerNorm 5) on the
        first-layer terms ``Σ x_i W_i + bias0`` (+ ``extra``, already a [rows, width] tensor)."""
        b = self.b
        (x0, w0), rest = terms[0], terms[1:]
        h = b.op("Gemm", [x0, b.const("W", w0), b.const("b", bias0)], "gemm")
        for x, w in rest:
            h = b.op("Add", [h, b.op("MatMul", [x, b.const("W", w)], "mm")], "add")
        if extra is not None:
            h = b.op("Add", [h, extra], "add")
        h = b.op("Relu", [h], "relu")
        h = self.gemm(h, self.w(f"{key}.2"), self.bias(f"{key}.2"), relu=True)
        if layer_norm:
            return self.layer_norm_linear(h, self.w(f"{key}.4"), self.bias(f"{key}.4"), f"{key}.5")
        return self.gemm(h, self.w(f"{key}.4"), self.bias(f"{key}.4")), None


def _layer_norm_scale(b: _Builder, sq: str, k: np.ndarray, eps: float) -> str:
    """``sqrt(sq · k + eps)`` [rows, L] for the squares ``sq`` [rows, L] and the
    weights ``k`` [L]: the sum to one column (a Gemm, ``eps`` its ``C``), its
    square root, widened to L columns by a MatMul with a row of ones (module
    doc)."""
    from onnx import helper

    std = b.op("Sqrt", [b.op("Gemm", [sq, b.const("Kvar", np.asarray(k).reshape(-1, 1)), b.const("eps", [eps])], "var_eps")], "std")
    out = b.name("std_wide")  # named before its constant: an export keeps the node names it always had
    b.nodes.append(helper.make_node("MatMul", [std, b.const("ones", np.ones((1, len(k))))], [out], name=f"{b.stage}/{out}"))
    return out


def _aggregation_switch(b: _Builder, latent: int) -> tuple[str, str]:
    """The two values every :func:`_aggregate` of a graph shares: the switch
    (bool scalar, true when ``in_edges`` has width 0: sum with ``ScatterND``)
    and the zero row [1, latent] the gather way's padding points at."""
    k = b.op("Shape", ["in_edges"], "k", start=1, end=2)  # [1]
    cond = b.op("Squeeze", [b.op("Equal", [k, b.const("k0", [0], np.int64)], "k_is_0")], "scatter_way")
    return cond, b.const("zero_row", np.zeros((1, latent)))


def _aggregate(b: _Builder, et: str, zeros_nl: str, recv2: str, switch: tuple[str, str]) -> str:
    """``Σ_{edges e into i} et[e]`` [N, latent] of the edge latents ``et``
    [E, latent] (module doc): an ``If`` on ``switch`` (:func:`_aggregation_switch`)
    between ``ScatterND(zeros_nl, recv2, et, reduction="add")`` (``zeros_nl``
    [N, latent] zeros, ``recv2`` the receivers [E, 1]) and the gather way over
    ``in_edges`` (rows of ``et`` and a zero row at index E, summed over K)."""
    from onnx import TensorProto, helper

    cond, zero_row = switch
    out = b.name("agg")
    outer = b.nodes
    b.nodes = []
    t = b.op("ScatterND", [zeros_nl, recv2, et], "agg_scatter", reduction="add")
    scatter_way = helper.make_graph(b.nodes, b.name("scatter_way"), [], [helper.make_tensor_value_info(t, TensorProto.FLOAT, None)])
    b.nodes = []
    padded = b.op("Concat", [et, zero_row], "agg_padded_rows", axis=0)  # [E + 1, latent]: row E is the padding
    g = b.op("Gather", [padded, "in_edges"], "agg_rows", axis=0)  # [N, K, latent]
    e = b.op("ReduceSum", [g, b.const("axK", [1], np.int64)], "agg_gather", keepdims=0)
    gather_way = helper.make_graph(b.nodes, b.name("gather_way"), [], [helper.make_tensor_value_info(e, TensorProto.FLOAT, None)])
    b.nodes = outer
    b.nodes.append(helper.make_node("If", [cond], [out], name=f"{b.stage}/{out}", then_branch=scatter_way, else_branch=gather_way))
    return out


def _state_dict_numpy(model: Any) -> dict[str, np.ndarray]:
    return {k: v.detach().cpu().numpy() for k, v in remap_legacy_state_dict(model.state_dict()).items()}


def inference_graph(model: Any, metadata_json: str | None = None) -> Any:
    """The ONNX inference graph (``onnx.ModelProto``, opset :data:`OPSET`) of a
    :class:`~hybridmpm.train.gns.model.GnsModel` (or a pre-split one: its state
    dict is remapped), computing ``model.forward`` on the inputs of the module
    doc. ``metadata_json``, if given, is stored as the ``hybridmpm`` metadata
    property. Raises ``KeyError`` for a state dict without the GNS keys."""
    from onnx import TensorProto, helper

    cfg = model.config
    dim, t_in, latent, layers = int(cfg.dim), int(cfg.t_in), int(cfg.latent), int(cfg.layers)
    sd = _state_dict_numpy(model)
    c = _Compiler(sd, LN_EPS)
    b = c.b
    f = "features."
    g = "gnn."
    inv_r = 1.0 / float(cfg.radius)

    # ---- node features: Δp (normalisation folded), walls, type table
    pos = "positions"
    last = b.op("Gather", [pos, b.const("i_last", np.int64(t_in - 1), np.int64)], "last", axis=0)
    prev = b.op("Gather", [pos, b.const("i_prev", np.int64(t_in - 2), np.int64)], "prev", axis=0)
    ax0 = b.const("ax0", [0], np.int64)
    newer = b.op("Slice", [pos, b.const("s1", [1], np.int64), b.const("e1", [t_in], np.int64), ax0], "newer")
    older = b.op("Slice", [pos, b.const("s0", [0], np.int64), b.const("e0", [t_in - 1], np.int64), ax0], "older")
    dp = b.op("Sub", [newer, older], "dp")  # [t_in-1, N, D]
    dp = b.op("Transpose", [dp], "dp_t", perm=[1, 0, 2])
    dp = b.op("Reshape", [dp, b.const("shape_v", [0, (t_in - 1) * dim], np.int64)], "vel_raw")  # [N, (t_in-1)·D]
    lower, upper = _vec(sd[f + "lower"]), _vec(sd[f + "upper"])
    # walls saturate at wall_reach·R (1 for models that predate the setting: GNS's clip at R)
    inv_w = 1.0 / (float(cfg.radius) * float(getattr(cfg, "wall_reach", 1.0)))
    lo = b.op("Mul", [b.op("Sub", [last, b.const("lower", lower)]), b.const("invR", np.float32(inv_w))], "wall_lo")
    hi = b.op("Mul", [b.op("Sub", [b.const("upper", upper), last]), b.const("invR", np.float32(inv_w))], "wall_hi")
    walls = b.op("Clip", [b.op("Concat", [lo, hi], "walls_raw", axis=1), b.const("m1", np.float32(-1)), b.const("p1", np.float32(1))], "walls")
    node_in = b.op("Concat", [dp, walls], "node_in", axis=1)
    w0 = c.w(g + "node_encoder.0")  # rows: velocities, walls, embedding
    nv = (t_in - 1) * dim
    vel_mean, vel_std = _vec(sd[f + "vel_mean"]), _vec(sd[f + "vel_std"])
    s_rep, m_rep = np.tile(vel_std, t_in - 1), np.tile(vel_mean, t_in - 1)
    w_vel = w0[:nv] / s_rep[:, None]
    bias0 = c.bias(g + "node_encoder.0") - (m_rep / s_rep) @ w0[:nv]
    w_nodes = np.concatenate([w_vel, w0[nv : nv + 2 * dim]], axis=0)
    table = np.asarray(sd[f + "embed.weight"], np.float64) @ w0[nv + 2 * dim :]  # [types, latent]
    type_term = b.op("Gather", [b.const("type_table", table), "particle_type"], "type_term", axis=0)
    b.stage = "node_encoder"
    h: Latent = c.mlp([(node_in, w_nodes)], bias0, g + "node_encoder", True, extra=type_term)
    branch = getattr(model, "branch", None) is not None
    if branch:  # the grid branch's context (hybridmpm.neural.grid_branch), gathered outside, joins the node latents
        h = (b.op("Add", [h[0], CONTEXT_INPUT], "h_context"), h[1])

    # ---- edge features from the radius-graph pass (1/R folded)
    b.stage = "edge_encoder"
    dist = b.op("Unsqueeze", ["distance", b.const("ax1", [1], np.int64)], "dist")
    e_in = b.op("Concat", ["displacement", dist], "edge_in", axis=1)
    e: Latent = c.mlp([(e_in, c.w(g + "edge_encoder.0") * inv_r)], c.bias(g + "edge_encoder.0"), g + "edge_encoder", True)

    # ---- processor
    b.stage = "aggregate"
    recv = "receivers"
    recv2 = b.op("Unsqueeze", [recv, b.const("ax1", [1], np.int64)], "recv2")
    n_shape = b.op("Shape", [last], "n_shape", end=1)  # [N]
    zeros_nl = b.op(
        "ConstantOfShape", [b.op("Concat", [n_shape, b.const("L", [latent], np.int64)], "nl", axis=0)], "zeros_nl",
        value=helper.make_tensor("z", TensorProto.FLOAT, [1], [0.0]),
    )  # fmt: skip
    switch = _aggregation_switch(b, latent)
    degree = "in_degree"  # [N, 1] edges into each node
    for k in range(layers):
        eb, nb = f"{g}edge_blocks.{k}.", f"{g}node_blocks.{k}."
        # edge update: e += LN(MLP(W_e e + (W_r h)[r] + (W_s h)[s]))
        b.stage = "edge_mlp"
        w_e, w_r, w_s = c.w(eb + "w_e"), c.w(eb + "w_r"), c.w(eb + "w_s")
        (et, ec), (ht, hc) = e, h
        bias = c.bias(eb + "w_e") + (0 if ec is None else ec @ w_e) + (0 if hc is None else hc @ (w_r + w_s))
        # the bias rides on the receiver projection (N rows) and the gathered sum is Gemm's C input: no extra edge pass
        pr = b.op("Gather", [b.op("Gemm", [ht, b.const("Wr", w_r), b.const("be", bias)], "hr"), recv], "hr_e", axis=0)
        ps = b.op("Gather", [b.op("MatMul", [ht, b.const("Ws", w_s)], "hs"), "senders"], "hs_e", axis=0)
        first = b.op("Gemm", [et, b.const("We", w_e), b.op("Add", [pr, ps], "hrs")], "first")
        x = c.gemm(b.op("Relu", [first]), c.w(eb + "rest.1"), c.bias(eb + "rest.1"), relu=True)
        y, beta = c.layer_norm_linear(x, c.w(eb + "rest.3"), c.bias(eb + "rest.3"), eb + "rest.4")
        e = (b.op("Add", [et, y], "e_res"), beta if ec is None else ec + beta)
        # node update: h += LN(MLP([h, Σ_{edges into i} e]))
        et, ec = e
        b.stage = "aggregate"
        agg = _aggregate(b, et, zeros_nl, recv2, switch)
        b.stage = "node_mlp"
        wn = c.w(nb + "0")
        w_h, w_a = wn[:latent], wn[latent:]
        terms, bias = c.linear_in([(h, w_h), ((agg, None), w_a)], c.bias(nb + "0"))
        assert ec is not None
        terms.append((degree, (ec @ w_a)[None, :]))  # Σ over deg_i edges of the carried row
        cat = b.op("Concat", [t for t, _ in terms], "node_cat", axis=1)
        y, beta = c.mlp([(cat, np.concatenate([w for _, w in terms], axis=0))], bias, nb[:-1], True)
        h = (b.op("Add", [ht, y], "h_res"), beta if hc is None else hc + beta)

    # ---- decoder (output statistics folded) and the Euler step
    b.stage = "decoder"
    ht, hc = h
    terms, bias = c.linear_in([(h, c.w(g + "decoder.0"))], c.bias(g + "decoder.0"))
    x = c.gemm(ht, terms[0][1], bias, relu=True)
    x = c.gemm(x, c.w(g + "decoder.2"), c.bias(g + "decoder.2"), relu=True)
    acc_mean, acc_std = _vec(sd[f + "acc_mean"]), _vec(sd[f + "acc_std"])
    acc = b.op("Gemm", [x, b.const("W", c.w(g + "decoder.4") * acc_std[None, :]), b.const("b", c.bias(g + "decoder.4") * acc_std + acc_mean)], "acc_raw")
    b.nodes.append(helper.make_node("Identity", [acc], ["acceleration"], name="decoder/acceleration"))
    nxt = b.op("Add", [b.op("Sub", [b.op("Add", [last, last]), prev], "inertia"), "acceleration"], "nxt")
    kin = b.op("Unsqueeze", [b.op("Equal", ["particle_type", b.const("kin", np.int64(GNS_KINEMATIC), np.int64)], "is_kin"), b.const("ax1", [1], np.int64)])
    b.nodes.append(helper.make_node("Where", [kin, last, nxt], ["next_position"], name="decoder/next_position"))

    return _model_proto(b, t_in, dim, latent, branch, metadata_json)


def _model_proto(b: _Builder, t_in: int, dim: int, latent: int, branch: bool, metadata_json: str | None) -> Any:
    """The ``onnx.ModelProto`` of the graph built in ``b``: the inputs and outputs of the module doc (``context`` with a grid
    ``branch``), opset :data:`OPSET`, ``metadata_json`` as the ``hybridmpm`` property."""
    from onnx import TensorProto, helper

    f32, i64 = TensorProto.FLOAT, TensorProto.INT64
    inputs = [
        helper.make_tensor_value_info("positions", f32, [t_in, "N", dim]),
        helper.make_tensor_value_info("particle_type", i64, ["N"]),
        helper.make_tensor_value_info("senders", i64, ["E"]),
        helper.make_tensor_value_info("receivers", i64, ["E"]),
        helper.make_tensor_value_info("displacement", f32, ["E", dim]),
        helper.make_tensor_value_info("distance", f32, ["E"]),
        helper.make_tensor_value_info("in_edges", i64, ["N", "K"]),
        helper.make_tensor_value_info("in_degree", f32, ["N", 1]),
    ]
    if branch:
        inputs.append(helper.make_tensor_value_info(CONTEXT_INPUT, f32, ["N", latent]))
    outputs = [helper.make_tensor_value_info("acceleration", f32, ["N", dim]), helper.make_tensor_value_info("next_position", f32, ["N", dim])]
    graph = helper.make_graph(b.nodes, "gns_step", inputs, outputs, initializer=b.inits)
    proto = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="hybridmpm")
    proto.ir_version = 9
    if metadata_json is not None:
        entry = proto.metadata_props.add()
        entry.key = METADATA_KEY
        entry.value = metadata_json
    return proto


def state_dict_from_onnx(path: Any) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Weights and metadata of a GNS exported by torch's ONNX exporter (graphs
    without the ``graph`` metadata key, before the compiled graph): the
    initializers named as the pre-split state dict (``node_encoder.0.weight``,
    ``vel_std``, ...), remapped to :class:`~hybridmpm.train.gns.model.GnsModel`
    keys. Raises ``ValueError`` for a compiled graph of any layout (its weights
    are folded: only its training run can export it again), ``KeyError`` for a
    file without the ``hybridmpm`` metadata."""
    import json

    import onnx
    from onnx import numpy_helper

    proto = onnx.load(str(path))
    meta = json.loads({p.key: p.value for p in proto.metadata_props}[METADATA_KEY])
    if "graph" in meta:
        raise ValueError(
            f"{path}: a compiled graph (layout {meta['graph']!r}); its weights are folded and cannot be read back: re-export it from its training run"
        )
    inits = {i.name: numpy_helper.to_array(i) for i in proto.graph.initializer}
    return remap_legacy_state_dict({k: v for k, v in inits.items() if not k.startswith("val_")}), meta


__all__ = ["GRAPH_LAYOUT", "INPUT_NAMES", "MIN_GAIN", "OPSET", "OUTPUT_NAMES", "STAGES", "inference_graph", "state_dict_from_onnx"]
