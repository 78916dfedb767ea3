"""Fused kernels for the compiled inference graph.

The compiled GNS graph (:mod:`hybridmpm.train.gns.onnx_graph`, layout
``compiled-3``) runs each edge-sized stage as a chain of onnxruntime
operators, one pass over an ``[E, 16]`` array each; at width 16 the passes,
not the arithmetic, bound a step (docs/neural.md, "What bounds it").
:func:`fuse_graph` rewrites such a graph so that five custom operators of
the domain :data:`DOMAIN` do each stage in one pass:

* ``HmpmEdgeEncoder`` replaces the edge encoder (``Concat`` of the edge
  geometry, three ``Gemm`` s with their ``Relu`` s, the folded LayerNorm);
* ``HmpmEdgeBlock`` replaces one message-passing step's edge update (the
  two ``Gather`` s of the node projections, their ``Add``, three ``Gemm`` s,
  the folded LayerNorm, the residual ``Add``) **and** its sum over receivers
  (the ``If`` that picks ``ScatterND`` or the gather way).

* ``HmpmNodeBlock`` replaces one message-passing step's node update (the
  ``Concat`` of the node latent, its sum and its in-degree, three ``Gemm`` s
  with their ``Relu`` s, the folded LayerNorm, the residual ``Add``);
* ``HmpmNodeEncoder`` replaces the feature construction and the node
  encoder (the velocities from the position history, the clipped wall
  distances, the type-table ``Gather``, the MLP and its LayerNorm);
* ``HmpmDecoder`` replaces the decoder's MLP and the Euler step with its
  kinematic ``Where``.

Only the node projections of each edge block (a ``Gemm`` and a ``MatMul``)
stay onnxruntime operators. The kernels are Rust
(``rust/gnn``: ``edge_encoder``, ``edge_block``, ``node_block``), served by
the extension module itself, which is an onnxruntime custom-op library
(operators in ``rust/ort-ops``, exported by ``rust/python``): :func:`register` loads it into a
session's options. The weights stay in the graph as initializers, fed to
the operators as inputs. The shipped ``.onnx`` files are not changed (any
onnxruntime runs them); :class:`~hybridmpm.neural.GnsRuntime` runs the
fused graph instead (``fused=None``), on any number of onnxruntime threads
(the kernels cut their work into fixed parts run on the session's intra-op
pool, with the same bits on any thread count), taken from
:func:`fused_sibling` (written beside each shipped model by
:func:`write_fused`, so that serving needs no ``onnx`` package) or, for
other files, rewritten in memory when the ``onnx`` package is installed.

The result is the same function with other float32 rounding (the dot
products summed in another order, with FMA on AVX2 machines); the sum over
receivers adds in edge order like ``ScatterND`` on one thread
(``tests/test_fused.py`` holds the outputs to the unfused graph's within
float32 tolerance on every shipped model).
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm import _core

#: Domain of the fused operators (``rust/ort-ops``).
DOMAIN = "hybridmpm.gnn"
#: Latent width the kernels are compiled for.
LATENT = 16


def library_path() -> str:
    """Path of the custom-op library: the ``hybridmpm._core`` extension module."""

    return str(_core.__file__)


def register(options: Any) -> None:
    """Load the fused operators into onnxruntime ``SessionOptions``."""
    options.register_custom_ops_library(library_path())


class _Graph:
    """Producers, consumers and initializers of a graph, for matching."""

    def __init__(self, g: Any) -> None:
        from onnx import numpy_helper

        self.g = g
        self.inits = {i.name: i for i in g.initializer}
        self.array = lambda name: numpy_helper.to_array(self.inits[name])
        self.producer: dict[str, Any] = {}
        self.consumers: dict[str, list[Any]] = {}
        for n in g.node:
            for o in n.output:
                self.producer[o] = n
            for i in _reads(n):
                self.consumers.setdefault(i, []).append(n)

    def node(self, name: str, op_type: str) -> Any:
        n = self.producer.get(name)
        if n is None or n.op_type != op_type:
            raise _NoMatch(f"{name}: expected the output of a {op_type}")
        return n

    def gemm(self, name: str, bias: bool = True, width: int = LATENT) -> tuple[Any, str, str | None]:
        """The plain ``Gemm`` (no transposes, alpha = beta = 1) producing ``name``:
        ``(node, W initializer [in, width], C name)``."""
        n = self.node(name, "Gemm")
        for a in n.attribute:
            if a.name in ("transA", "transB") and a.i != 0 or a.name in ("alpha", "beta") and a.f != 1.0:
                raise _NoMatch(f"{n.name}: Gemm with {a.name}")
        if n.input[1] not in self.inits or len(self.array(n.input[1]).shape) != 2 or self.array(n.input[1]).shape[1] != width:
            raise _NoMatch(f"{n.name}: weight is not a [in, {width}] initializer")
        c = n.input[2] if len(n.input) > 2 and n.input[2] else None
        if bias and (c not in self.inits or self.array(c).shape != (LATENT,)):
            raise _NoMatch(f"{n.name}: bias is not a [{LATENT}] initializer")
        return n, n.input[1], c

    def layer_norm(self, name: str) -> tuple[list[Any], str, str, str]:
        """The folded LayerNorm ``z / sqrt(sq(z)·k + ε)`` producing ``name``:
        ``(nodes, z, k, ε)``."""
        div = self.node(name, "Div")
        z, std = div.input
        widen = self.node(std, "MatMul")
        if widen.input[1] not in self.inits or not np.array_equal(self.array(widen.input[1]), np.ones((1, LATENT), np.float32)):
            raise _NoMatch(f"{widen.name}: not a widening by a row of ones")
        sqrt = self.node(widen.input[0], "Sqrt")
        var, k, eps = self.gemm(sqrt.input[0], bias=False, width=1)
        if k not in self.inits or self.array(k).shape != (LATENT, 1) or eps is None or eps not in self.inits or self.array(eps).shape != (1,):
            raise _NoMatch(f"{var.name}: not a one-column variance")
        sq = self.node(var.input[0], "Mul")
        if list(sq.input) != [z, z]:
            raise _NoMatch(f"{sq.name}: not the square of {z}")
        return [div, widen, sqrt, var, sq], z, k, eps

    def mlp_tail(self, name: str) -> tuple[list[Any], str, list[str]]:
        """``relu(relu(x) W₂ + b₂) W₃ + b₃`` then the folded LayerNorm, ending
        at ``name``: ``(nodes, x, [w2, b2, w3, b3, k, ε])``."""
        ln_nodes, z, k, eps = self.layer_norm(name)
        g3, w3, b3 = self.gemm(z)
        r2 = self.node(g3.input[0], "Relu")
        g2, w2, b2 = self.gemm(r2.input[0])
        r1 = self.node(g2.input[0], "Relu")
        assert b2 is not None and b3 is not None
        return [*ln_nodes, g3, r2, g2, r1], r1.input[0], [w2, b2, w3, b3, k, eps]


class _NoMatch(Exception):
    """The graph is not of the form the fused operators replace."""


def _reads(n: Any) -> list[str]:
    """Every name node ``n`` reads, including those its subgraphs read from the outer scope."""
    names = [i for i in n.input if i]
    for a in n.attribute:
        if a.type == a.GRAPH:
            inner = {o for x in a.g.node for o in x.output} | {i.name for i in a.g.initializer}
            for x in a.g.node:
                names += [i for i in _reads(x) if i not in inner]
    return names


def fuse_graph(proto: Any) -> Any | None:
    """The ``onnx.ModelProto`` of a compiled GNS graph rewritten to use the
    fused operators (module doc), or ``None`` if the graph is not of that
    form (another layout, another latent width, a torch export): then the
    caller runs it unchanged. The input proto is not modified."""
    from onnx import helper

    _LAST_REASON[0] = ""
    m = type(proto)()
    m.CopyFrom(proto)
    g = m.graph
    try:
        G = _Graph(g)
        remove: list[Any] = []
        new: list[tuple[int, Any]] = []  # (position of the node it replaces, fused node)
        position = {id(n): i for i, n in enumerate(g.node)}

        # the edge encoder: Concat(displacement, Unsqueeze(distance)) -> MLP -> LayerNorm
        concats = [n for n in g.node if n.op_type == "Concat" and n.input and n.input[0] == "displacement"]
        if len(concats) != 1:
            raise _NoMatch("no single edge-encoder Concat of the displacement")
        concat = concats[0]
        unsq = G.node(concat.input[1], "Unsqueeze")
        if unsq.input[0] != "distance":
            raise _NoMatch("edge encoder: second input is not the distance")
        g1_users = G.consumers.get(concat.output[0], [])
        if len(g1_users) != 1 or g1_users[0].op_type != "Gemm":
            raise _NoMatch("edge encoder: Concat does not feed one Gemm")
        g1, w1, b1 = G.gemm(g1_users[0].output[0])
        assert b1 is not None  # gemm() checked the bias
        relu1 = [n for n in G.consumers.get(g1.output[0], []) if n.op_type == "Relu"]
        # find the encoder's LayerNorm output: follow relu -> gemm -> relu -> gemm -> ... -> Div
        enc_out = None
        for n in g.node:
            if n.op_type == "Div":
                try:
                    nodes, x, ws = G.mlp_tail(n.output[0])
                except _NoMatch:
                    continue
                if x == g1.output[0]:
                    enc_out, enc_nodes, enc_ws = n.output[0], nodes, ws
                    break
        if enc_out is None or len(relu1) != 1:
            raise _NoMatch("edge encoder: no MLP with a folded LayerNorm after the first Gemm")
        enc = helper.make_node("HmpmEdgeEncoder", ["displacement", "distance", w1, b1, *enc_ws], [enc_out], name="edge_encoder/fused", domain=DOMAIN)
        enc_remove = [concat, unsq, g1, *enc_nodes]
        remove += enc_remove
        new.append((position[id(g1)], enc))

        # every message-passing step: the If that sums over receivers, and the edge update it reads
        ifs = [n for n in g.node if n.op_type == "If" and n.name.startswith("aggregate/")]
        if not ifs:
            raise _NoMatch("no aggregation If")
        for agg in ifs:
            scatter = [x for a in agg.attribute if a.name == "then_branch" for x in a.g.node if x.op_type == "ScatterND"]
            if len(scatter) != 1:
                raise _NoMatch(f"{agg.name}: then-branch is not one ScatterND")
            e_res = scatter[0].input[2]
            res = G.node(e_res, "Add")
            found = None
            for ln_name, e_prev in ((res.input[1], res.input[0]), (res.input[0], res.input[1])):
                try:  # the residual's MLP branch is the one whose first Gemm reads the other input
                    tail, first_out, ws = G.mlp_tail(ln_name)
                    first, we, hrs = G.gemm(first_out, bias=False)
                except _NoMatch:
                    continue
                if first.input[0] == e_prev and hrs is not None:
                    found = tail, ws, first, we, hrs, e_prev
                    break
            if found is None:
                raise _NoMatch(f"{res.name}: not e + LN(MLP(e W_e + gathered projections))")
            tail, ws, first, we, hrs, e_prev = found
            add = G.node(hrs, "Add")
            gr, gs = G.node(add.input[0], "Gather"), G.node(add.input[1], "Gather")
            if gr.input[1] != "receivers" or gs.input[1] != "senders" or any(a.name == "axis" and a.i != 0 for a in [*gr.attribute, *gs.attribute]):
                raise _NoMatch(f"{add.name}: not hr[receivers] + hs[senders] (row gathers)")
            block = helper.make_node(
                "HmpmEdgeBlock",
                [e_prev, gr.input[0], gs.input[0], "receivers", "senders", we, *ws],
                [e_res, agg.output[0]],
                name=f"edge_mlp/fused_{agg.name.split('/')[-1]}",
                domain=DOMAIN,
            )
            nodes = [gr, gs, add, first, *tail, res, agg]
            remove += nodes
            new.append((position[id(res)], block))

            # the node update that reads this sum: h + LN(MLP(Concat(h, agg, degree)))
            cats = [n for n in G.consumers.get(agg.output[0], []) if n.op_type == "Concat"]
            if len(cats) != 1 or len(cats[0].input) != 3 or cats[0].input[1] != agg.output[0]:
                raise _NoMatch(f"{agg.name}: its sum does not feed one Concat(h, agg, degree)")
            cat = cats[0]
            h_in, degree = cat.input[0], cat.input[2]
            users = G.consumers.get(cat.output[0], [])
            if len(users) != 1 or users[0].op_type != "Gemm":
                raise _NoMatch(f"{cat.name}: does not feed one Gemm")
            g1, w1, b1 = G.gemm(users[0].output[0])
            assert b1 is not None  # gemm() checked the bias
            if G.array(w1).shape != (2 * LATENT + 1, LATENT):
                raise _NoMatch(f"{g1.name}: weight is not [{2 * LATENT + 1}, {LATENT}]")
            node_res = None
            for r in G.consumers.get(h_in, []):
                if r.op_type != "Add" or h_in not in r.input:
                    continue
                ln_name = r.input[1] if r.input[0] == h_in else r.input[0]
                try:
                    tail, first_out, ws = G.mlp_tail(ln_name)
                except _NoMatch:
                    continue
                if first_out == g1.output[0]:
                    node_res = r, tail, ws
                    break
            if node_res is None:
                raise _NoMatch(f"{g1.name}: not h + LN(MLP(...)) after the Concat")
            r, tail, ws = node_res
            node = helper.make_node(
                "HmpmNodeBlock", [h_in, agg.output[0], degree, w1, b1, *ws], [r.output[0]], name=f"node_mlp/fused_{agg.name.split('/')[-1]}", domain=DOMAIN
            )
            remove += [cat, g1, *tail, r]
            new.append((position[id(r)], node))
        node_enc = _match_node_encoder(G)
        dec = _match_decoder(G)
        for nodes, at, fused_node in (node_enc, dec):
            remove += nodes
            new.append((position[id(at)], fused_node))
    except (_NoMatch, KeyError, IndexError, ValueError) as e:
        _LAST_REASON[0] = str(e)
        return None

    # the removed nodes' outputs must not be read elsewhere, except those the fused nodes produce
    gone = {id(n) for n in remove}
    produced = {o for _, n in new for o in n.output}
    for n in g.node:
        if id(n) in gone:
            continue
        for i in _reads(n):
            p = G.producer.get(i)
            if p is not None and id(p) in gone and i not in produced:
                _LAST_REASON[0] = f"{n.name} reads {i}, an intermediate of a fused stage"
                return None
    keep = [(i, n) for i, n in enumerate(g.node) if id(n) not in gone] + new
    keep.sort(key=lambda t: t[0])
    del g.node[:]
    g.node.extend(n for _, n in keep)
    _prune(g)
    m.opset_import.append(helper.make_opsetid(DOMAIN, 1))
    return m


def _scalar(G: _Graph, name: str, dtype: Any) -> Any:
    """The value of a scalar (or one-element) initializer ``name`` of ``dtype``."""
    if name not in G.inits:
        raise _NoMatch(f"{name}: not an initializer")
    a = G.array(name)
    if a.dtype != dtype or a.size != 1:
        raise _NoMatch(f"{name}: not a {dtype} scalar")
    return a.reshape(()).item()


def _history_gather(G: _Graph, name: str, t: int) -> None:
    """Check that ``name`` is ``positions[t]`` (a Gather on axis 0)."""
    n = G.node(name, "Gather")
    if n.input[0] != "positions" or _scalar(G, n.input[1], np.int64) != t or any(a.name == "axis" and a.i != 0 for a in n.attribute):
        raise _NoMatch(f"{n.name}: not positions[{t}]")


def _history_len(G: _Graph) -> tuple[int, int]:
    """``(t_in, dim)`` of the graph's ``positions`` input ``[t_in, N, dim]``."""
    inp = [i for i in G.g.input if i.name == "positions"]
    if len(inp) != 1:
        raise _NoMatch("no positions input")
    dims = inp[0].type.tensor_type.shape.dim
    if len(dims) != 3 or not dims[0].HasField("dim_value") or not dims[2].HasField("dim_value"):
        raise _NoMatch("positions: not [t_in, N, dim] with t_in and dim fixed")
    return int(dims[0].dim_value), int(dims[2].dim_value)


def _match_node_encoder(G: _Graph) -> tuple[list[Any], Any, Any]:
    """The feature construction and node encoder (:mod:`hybridmpm.train.gns.onnx_graph`):
    ``LN(MLP(Concat(velocities, walls)) + table[particle_type])``, checked node by
    node. Returns ``(nodes to remove, node whose place it takes, HmpmNodeEncoder)``;
    the feature nodes left dead are pruned."""
    from onnx import helper

    t_in, dim = _history_len(G)
    if (t_in - 1) * dim + 2 * dim > 32:
        raise _NoMatch("node encoder: more than 32 node features")
    types = [n for n in G.g.node if n.op_type == "Gather" and list(n.input[1:]) == ["particle_type"]]
    if len(types) != 1 or types[0].input[0] not in G.inits:
        raise _NoMatch("node encoder: no single type-table Gather")
    type_node = types[0]
    table = type_node.input[0]
    if G.array(table).ndim != 2 or G.array(table).shape[1] != LATENT:
        raise _NoMatch(f"{table}: not a [types, {LATENT}] table")
    adds = [n for n in G.consumers.get(type_node.output[0], []) if n.op_type == "Add"]
    if len(adds) != 1:
        raise _NoMatch("node encoder: the type term does not feed one Add")
    add = adds[0]
    g1, w1, b1 = G.gemm(add.input[0] if add.input[1] == type_node.output[0] else add.input[1])
    assert b1 is not None  # gemm() checked the bias
    node_in = G.node(g1.input[0], "Concat")
    vel, walls = node_in.input
    # velocities: Reshape(Transpose(Sub(positions[1:t_in], positions[0:t_in-1]), [1, 0, 2]), [0, (t_in-1)·dim])
    reshape = G.node(vel, "Reshape")
    if list(G.array(reshape.input[1])) != [0, (t_in - 1) * dim]:
        raise _NoMatch(f"{reshape.name}: not [N, (t_in - 1)·dim]")
    tr = G.node(reshape.input[0], "Transpose")
    if [list(a.ints) for a in tr.attribute if a.name == "perm"] != [[1, 0, 2]]:
        raise _NoMatch(f"{tr.name}: not perm [1, 0, 2]")
    sub = G.node(tr.input[0], "Sub")
    for name, (lo, hi) in zip(sub.input, ((1, t_in), (0, t_in - 1))):
        sl = G.node(name, "Slice")
        if sl.input[0] != "positions" or [list(G.array(i)) for i in sl.input[1:4]] != [[lo], [hi], [0]]:
            raise _NoMatch(f"{sl.name}: not positions[{lo}:{hi}]")
    # walls: Clip(Concat((last - lower)·w, (upper - last)·w), -1, 1)
    clip = G.node(walls, "Clip")
    if _scalar(G, clip.input[1], np.float32) != -1.0 or _scalar(G, clip.input[2], np.float32) != 1.0:
        raise _NoMatch(f"{clip.name}: not a clip to [-1, 1]")
    wcat = G.node(clip.input[0], "Concat")
    inv = []
    bounds = []
    for name, last_first in zip(wcat.input, (True, False)):
        mul = G.node(name, "Mul")
        d = G.node(mul.input[0], "Sub")
        inv.append(_scalar(G, mul.input[1], np.float32))
        last, bound = (d.input[0], d.input[1]) if last_first else (d.input[1], d.input[0])
        _history_gather(G, last, t_in - 1)
        if bound not in G.inits or G.array(bound).shape != (dim,):
            raise _NoMatch(f"{d.name}: bound is not a [{dim}] initializer")
        bounds.append(bound)
    if inv[0] != inv[1]:
        raise _NoMatch("walls: two different scales")
    inv_w = G.producer[wcat.input[0]].input[1]
    if G.array(w1).shape != ((t_in - 1) * dim + 2 * dim, LATENT):
        raise _NoMatch(f"{g1.name}: weight is not [(t_in - 1)·dim + 2·dim, {LATENT}]")
    out = None
    for n in G.g.node:
        if n.op_type == "Div":
            try:
                tail, x, ws = G.mlp_tail(n.output[0])
            except _NoMatch:
                continue
            if x == add.output[0]:
                out = n, tail, ws
                break
    if out is None:
        raise _NoMatch("node encoder: no MLP with a folded LayerNorm after the type term")
    div, tail, ws = out
    node = helper.make_node(
        "HmpmNodeEncoder",
        ["positions", "particle_type", bounds[0], bounds[1], inv_w, table, w1, b1, *ws],
        [div.output[0]],
        name="node_encoder/fused",
        domain=DOMAIN,
    )
    return [g1, add, *tail], div, node


def _match_decoder(G: _Graph) -> tuple[list[Any], Any, Any]:
    """The decoder and the Euler step: ``acceleration = MLP(h)`` (two ``Relu``
    layers and a linear one to D), ``next_position = Where(type == kinematic,
    last, (last + last) − prev + acceleration)``. Returns ``(nodes to remove,
    node whose place it takes, HmpmDecoder)``."""
    from onnx import helper

    t_in, dim = _history_len(G)
    where = G.node("next_position", "Where")
    cond, last, nxt = where.input
    _history_gather(G, last, t_in - 1)
    unsq = G.node(cond, "Unsqueeze")
    eq = G.node(unsq.input[0], "Equal")
    if eq.input[0] != "particle_type":
        raise _NoMatch(f"{eq.name}: not particle_type == kinematic")
    kin = eq.input[1]
    _scalar(G, kin, np.int64)
    add_acc = G.node(nxt, "Add")
    if add_acc.input[1] != "acceleration":
        raise _NoMatch(f"{add_acc.name}: not inertia + acceleration")
    inertia = G.node(add_acc.input[0], "Sub")
    twice = G.node(inertia.input[0], "Add")
    if list(twice.input) != [last, last]:
        raise _NoMatch(f"{twice.name}: not last + last")
    _history_gather(G, inertia.input[1], t_in - 2)
    ident = G.node("acceleration", "Identity")
    g3 = G.node(ident.input[0], "Gemm")
    w3, b3 = g3.input[1], g3.input[2] if len(g3.input) > 2 else ""
    if w3 not in G.inits or G.array(w3).shape != (LATENT, dim) or b3 not in G.inits or G.array(b3).shape != (dim,):
        raise _NoMatch(f"{g3.name}: not [{LATENT}, {dim}] with a bias")
    if any(a.name in ("transA", "transB") and a.i != 0 or a.name in ("alpha", "beta") and a.f != 1.0 for a in g3.attribute):
        raise _NoMatch(f"{g3.name}: Gemm with transposes or scales")
    r2 = G.node(g3.input[0], "Relu")
    g2, w2, b2 = G.gemm(r2.input[0])
    r1 = G.node(g2.input[0], "Relu")
    g1, w1, b1 = G.gemm(r1.input[0])
    assert b1 is not None and b2 is not None  # gemm() checked the biases
    node = helper.make_node(
        "HmpmDecoder",
        [g1.input[0], "positions", "particle_type", kin, w1, b1, w2, b2, w3, b3],
        ["acceleration", "next_position"],
        name="decoder/fused",
        domain=DOMAIN,
    )
    return [g1, r1, g2, r2, g3, ident, twice, inertia, add_acc, eq, unsq, where], where, node


#: Why the last :func:`fuse_graph` returned ``None`` (for messages and tests).
_LAST_REASON = [""]

#: Metadata key of a fused file: the SHA-256 of the file it was made from.
SOURCE_KEY = "hybridmpm_fused_source_sha256"


def why_not() -> str:
    """Why the last :func:`fuse_graph` returned ``None``."""
    return _LAST_REASON[0] or "no onnx package to rewrite it with"


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def fused_sibling(path: Path) -> Path:
    """Where the fused graph of the model file ``path`` is kept: ``fused/<name>`` beside it."""
    return path.parent / "fused" / path.name


def write_fused(path: str | Path) -> Path | None:
    """Write the fused graph of the model file ``path`` to :func:`fused_sibling`
    (needs the ``onnx`` package), recording the source's SHA-256 in its
    metadata (:data:`SOURCE_KEY`); returns the file written, or ``None`` (and
    removes a stale one) when the graph is not of the fusable form."""
    import onnx

    path = Path(path)
    out = fused_sibling(path)
    proto = fuse_graph(onnx.load(str(path)))
    if proto is None:
        out.unlink(missing_ok=True)
        return None
    entry = proto.metadata_props.add()
    entry.key, entry.value = SOURCE_KEY, sha256(path)
    out.parent.mkdir(exist_ok=True)
    out.write_bytes(proto.SerializeToString())
    return out


def load_fused(path: Path) -> bytes | None:
    """The serialised fused graph of the model file ``path``: its
    :func:`fused_sibling` if that was made from this very file (SHA-256), else
    the in-memory rewrite if the ``onnx`` package is installed, else ``None``."""
    sib = fused_sibling(path)
    if sib.is_file():
        data = sib.read_bytes()
        if _sibling_source(data) == sha256(path):
            return data
    try:
        import onnx
    except ImportError:
        _LAST_REASON[0] = "no fused file beside it and no onnx package to rewrite it with"
        return None
    try:
        proto = onnx.load(str(path))
    except Exception as e:  # noqa: BLE001 - not an ONNX file: the plain session reports it
        _LAST_REASON[0] = f"not readable by onnx ({e})"
        return None
    out = fuse_graph(proto)
    return None if out is None else out.SerializeToString()


def _sibling_source(data: bytes) -> str | None:
    """The :data:`SOURCE_KEY` metadata of a serialised fused graph, read with
    onnxruntime alone (no ``onnx`` package)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    register(opts)
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    try:
        s = ort.InferenceSession(data, opts, providers=["CPUExecutionProvider"])
    except Exception:  # noqa: BLE001 - a damaged sibling is ignored
        return None
    return s.get_modelmeta().custom_metadata_map.get(SOURCE_KEY)


def _prune(g: Any) -> None:
    """Drop nodes whose outputs nothing reads (the aggregation switch the
    fused sums made dead), and initializers no node reads."""
    outputs = {o.name for o in g.output}
    while True:
        read = {i for n in g.node for i in _reads(n)} | outputs
        dead = [n for n in g.node if not any(o in read for o in n.output)]
        if not dead:
            break
        for n in dead:
            g.node.remove(n)
    read = {i for n in g.node for i in _reads(n)}
    unused = [i for i in g.initializer if i.name not in read]
    for i in unused:
        g.initializer.remove(i)


__all__ = ["DOMAIN", "LATENT", "SOURCE_KEY", "fuse_graph", "fused_sibling", "library_path", "load_fused", "register", "why_not", "write_fused"]
