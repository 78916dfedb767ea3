"""The network at run time: numpy + onnxruntime (no torch).

:class:`GnsRuntime` wraps an exported GNS (see :mod:`hybridmpm.train.gns.export`)
and its metadata, and predicts one model step (``r_t`` frames) from a position
history (paper Sec. 2.2, App. A). The simulator that rolls it out is
:class:`hybridmpm.sim.NeuralSimulator`.
"""

from __future__ import annotations

import functools
import json
import math
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.conventions import GNS_KINEMATIC, T_IN
from hybridmpm.errors import InvalidInputError
from hybridmpm.files import check_model_file
from hybridmpm.graph import radius_graph
from hybridmpm.neural import fused
from hybridmpm.neural.constants import BRANCH_KEY, CONTEXT_INPUT, FEATURE_VERSION, GRAPH_LAYOUT, INPUT_NAMES, METADATA_KEY, NUM_TYPES
from hybridmpm.neural.grid_branch import GridBranchRuntime


@functools.lru_cache(maxsize=32)
def _fused_cached(path: str, mtime_ns: int, size: int) -> bytes | None:
    return fused.load_fused(Path(path))


def _fused_bytes(path: Path) -> bytes | None:
    """The fused graph of the model file at ``path`` (:func:`hybridmpm.neural.fused.load_fused`),
    or None; cached per file version (sessions of the same model are made often)."""
    st = path.stat()
    return _fused_cached(str(path), st.st_mtime_ns, st.st_size)


def _check_meta(meta: dict[str, Any], path: Path) -> dict[str, Any]:
    """The metadata keys the runtime uses, checked (``model.<key>`` names the
    bad one); returns ``meta`` with the defaults of old exports filled in."""

    def bad(key: str, what: str) -> InvalidInputError:
        return InvalidInputError(f"model.{key}: {path.name} has {key} = {meta.get(key)!r}, expected {what}", f"model.{key}")

    def number(key: str) -> float:
        v = meta.get(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise bad(key, "a finite number")
        return float(v)

    def integer(key: str, lo: int) -> int:
        v = meta.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            raise bad(key, f"an integer >= {lo}")
        return v

    meta.setdefault("r_t", 1)
    meta.setdefault("r_p", 1.0)
    meta.setdefault("t_in", T_IN)
    if meta.get("dim") not in (2, 3) or isinstance(meta.get("dim"), bool):
        raise bad("dim", "2 or 3")
    if not number("radius") > 0:
        raise bad("radius", "> 0 [m]")
    if not 0 < number("r_p") <= 1:
        raise bad("r_p", "a number in (0, 1]")
    integer("r_t", 1)
    integer("t_in", 3)
    b = meta.get("bounds")
    try:
        arr = np.asarray(b, np.float64)
    except (TypeError, ValueError):
        raise bad("bounds", f"[[lo, hi]] * {meta['dim']}") from None
    if arr.shape != (meta["dim"], 2) or not np.isfinite(arr).all() or not (arr[:, 0] < arr[:, 1]).all():
        raise bad("bounds", f"[[lo, hi]] * {meta['dim']} with lo < hi")
    types = meta.get("particle_types", [])
    if not isinstance(types, list) or not all(isinstance(t, int) and not isinstance(t, bool) for t in types):
        raise bad("particle_types", "a list of integers")
    return meta


#: The gather way's [N, K] table of in-edges (:func:`aggregation_inputs`) may hold at most this many
#: times the edges, or :data:`SMALL_TABLE` entries, whichever is more; a graph with more uneven
#: in-degrees (a few crowded nodes) is summed the ScatterND way on one thread instead, so that the
#: table never outgrows the edge arrays by more.
MAX_PADDING = 4
#: Entries of an [N, K] table that is always small enough (4 MB of gathered latents at width 16).
SMALL_TABLE = 1 << 16


def aggregation_inputs(receivers: np.ndarray, n: int, gather: bool) -> tuple[np.ndarray, np.ndarray]:
    """The aggregation inputs of a compiled GNS graph (:mod:`hybridmpm.train.gns.onnx_graph`,
    module doc) for ``receivers`` int64 [E] (values in ``[0, n)``, any order):
    ``(in_edges, in_degree)``. ``in_degree`` float32 [n, 1] counts the edges into
    each node. ``in_edges`` int64 [n, K], K the largest in-degree, lists in row i
    the ids of the edges into node i (in edge order), padded with E (the zero
    row the graph appends); it has width 0, meaning "sum with ``ScatterND``"
    (exact on one onnxruntime thread only), when ``gather`` is false, when
    there are no edges, or when ``n·K`` exceeds both :data:`MAX_PADDING` times
    the edges and :data:`SMALL_TABLE`."""
    e = receivers.size
    deg = np.bincount(receivers, minlength=n)
    in_degree = deg.astype(np.float32)[:, None]
    k = int(deg.max()) if e else 0
    if not gather or k == 0 or n * k > max(MAX_PADDING * e, SMALL_TABLE):
        return np.zeros((n, 0), np.int64), in_degree
    # in place, one [n, K] array (numpy's large temporaries each cost fresh pages: 4x slower)
    pos = np.empty((n, k), np.int64)
    pos[:] = np.arange(k)
    pad = pos >= deg[:, None]
    pos += (np.cumsum(deg) - deg)[:, None]
    if np.any(receivers[1:] < receivers[:-1]):  # radius_graph sorts by receiver; a graph from elsewhere may not be
        real = ~pad
        pos[real] = np.argsort(receivers, kind="stable")[pos[real]]
    pos[pad] = e
    return pos, in_degree


class GnsRuntime:
    """An exported GNS model loaded into onnxruntime.

    ``path`` an ``.onnx`` file written by :func:`~hybridmpm.train.gns.export.export_onnx`;
    ``threads`` onnxruntime intra-op threads (1 leaves a core to MPM; 0
    onnxruntime's default, one per core); ``spinning`` whether the worker
    threads busy-wait for work (default: for any count but 1, 0 included).
    The fused kernels (:mod:`hybridmpm.neural.fused`) run their parts on
    these threads with the same bits on any count: on the scene states two
    spinning threads make the whole network step up to 1.35× faster than
    one (water2d's 500 particles: 1.03×; the ONNX graph alone 1.7–1.8× on
    2 400-particle blocks),
    ``benchmarks/results/inference.md``; the price is a
    worker that keeps spinning for tens of ms after each step, which slows an
    MPM step run right after by up to ~20%. So: two threads for the network
    alone (MPM idle), one in the hybrid and the service (the default). A
    plain (unfused) graph on more than one thread sums over receivers the
    gather way (:mod:`hybridmpm.train.gns.onnx_graph`): onnxruntime's ``ScatterND``
    loses updates there. A graph of torch's exporter (no ``graph`` in its
    metadata), which has only the ``ScatterND`` sum, runs on one thread
    whatever ``threads`` says, with a ``UserWarning``
    (:func:`hybridmpm.train.gns.export.upgrade_onnx` rewrites it as the
    compiled graph of the same weights). A compiled graph of a layout other
    than :data:`~hybridmpm.neural.constants.GRAPH_LAYOUT` is refused: its
    training run exports it again.
    ``meta`` holds the model's metadata: ``scene``,
    ``dim``, ``radius`` R [m], ``r_p``, ``r_t``, ``t_in``, ``particle_types``,
    ``feature_version``, ``data_sha256``, architecture and errors.
    Raises :class:`InvalidInputError` (field ``model``) for a missing or
    foreign file, one that is not a regular file (a FIFO, a device such as
    ``/dev/zero``) or larger than
    :data:`~hybridmpm.files.MAX_MODEL_BYTES`, a compiled graph of another layout or an incompatible
    feature version, (``fused``) for ``fused=True`` on a graph the fused
    kernels do not replace, (``model.<key>``) for
    metadata out of range (e.g. ``r_p`` NaN or outside (0, 1]), (``threads``)
    for a thread count that is not an integer in [0, 256]. ``profile``
    switches onnxruntime's profiler on (for benchmarks).
    """

    #: Its input is a radius graph of the particles (:class:`hybridmpm.neural.base.Runtime`).
    needs_graph = True

    def __init__(self, path: str | Path, threads: int = 1, spinning: bool | None = None, profile: bool = False, fused: bool | None = None) -> None:
        if isinstance(threads, bool) or not isinstance(threads, int) or not 0 <= threads <= 256:
            raise InvalidInputError(f"threads: must be an integer in [0, 256] (0: onnxruntime's default, one per core), got {threads!r}", "threads")
        if fused is not None and not isinstance(fused, bool):
            raise InvalidInputError(f"fused: must be True, False or None (automatic), got {fused!r}", "fused")
        self.threads = threads
        self._fused_asked = fused
        #: Why the fused kernels do not replace this file's graph, when ``fused=True`` asked for them (refused
        #: once the metadata is checked, so that a file of another layout is named as such first).
        self._not_fused: str | None = None
        #: Whether the session runs the fused edge kernels (:mod:`hybridmpm.neural.fused`).
        self.fused = False
        #: Whether onnxruntime's worker threads busy-wait (see the class doc).
        self.spinning = bool(threads != 1 if spinning is None else spinning)
        self.path = Path(path)
        check_model_file(self.path)  # a regular file of at most MAX_MODEL_BYTES (a FIFO, /dev/zero refused without blocking), before onnxruntime reads it
        self._profile = profile
        self.session = self._session(threads)
        self._serial: Any = None
        raw = self.session.get_modelmeta().custom_metadata_map.get(METADATA_KEY)
        if raw is None:
            raise InvalidInputError(f"model: {self.path} has no '{METADATA_KEY}' metadata (not exported by hybridmpm)", "model")
        try:
            meta = json.loads(raw)
        except ValueError as e:
            raise InvalidInputError(f"model: the '{METADATA_KEY}' metadata of {self.path} is not JSON ({e})", "model") from e
        if not isinstance(meta, dict):
            raise InvalidInputError(f"model: the '{METADATA_KEY}' metadata of {self.path} is not a JSON object", "model")
        if "graph" in meta and meta["graph"] != GRAPH_LAYOUT:
            raise InvalidInputError(
                f"model: {self.path} is a compiled graph of layout {meta['graph']!r}, which this hybridmpm no longer runs (it runs {GRAPH_LAYOUT!r}): "
                "re-export it from its training run (`hybridmpm train` with the same --out resumes at its last step and writes model.onnx again)",
                "model",
            )
        if meta.get("feature_version") != FEATURE_VERSION:
            raise InvalidInputError(f"model: feature version {meta.get('feature_version')} of {self.path} is not {FEATURE_VERSION} (this hybridmpm)", "model")
        self.meta: dict[str, Any] = _check_meta(meta, self.path)
        if self._not_fused is not None:
            raise InvalidInputError(f"fused: {self.path.name} is not a compiled graph the fused kernels replace ({self._not_fused})", "fused")
        #: The graph's input names: compiled graphs also take the edge geometry
        #: (``displacement``, ``distance``) and the aggregation inputs; graphs of torch's exporter only the first four.
        self.input_names: list[str] = [i.name for i in self.session.get_inputs()]
        unknown = sorted(set(self.input_names) - set(INPUT_NAMES))
        if unknown:
            raise InvalidInputError(f"model: {self.path.name} asks for inputs {unknown}, not among {list(INPUT_NAMES)}", "model")
        #: The grid branch (:class:`hybridmpm.neural.grid_branch.GridBranchRuntime`) of a GNS trained with one, else None.
        self.branch: Any = None
        if (BRANCH_KEY in self.meta) != (CONTEXT_INPUT in self.input_names):
            raise InvalidInputError(f"model.{BRANCH_KEY}: {self.path.name} has a grid branch in its metadata or its graph, not both", f"model.{BRANCH_KEY}")
        if BRANCH_KEY in self.meta:
            self.branch = GridBranchRuntime(self.meta[BRANCH_KEY], self.meta, max(threads, 1) if threads else 0)
        if threads != 1 and "in_edges" not in self.input_names:
            warnings.warn(
                f"threads: {self.path.name} has no in_edges input (a graph of torch's exporter): it sums over receivers with onnxruntime's "
                "ScatterND only, which loses updates on more than one thread (microsoft/onnxruntime#23396): running it on one thread; "
                "hybridmpm.train.gns.export.upgrade_onnx rewrites it for any thread count",
                UserWarning,
                stacklevel=2,
            )
            self.threads, self.spinning = 1, False
            self.session = self._session(1)

    def _session(self, threads: int) -> Any:
        """An onnxruntime session of the file on ``threads`` intra-op threads
        (spinning as :attr:`spinning` says; one thread never spins): of its
        fused graph (:mod:`hybridmpm.neural.fused`) unless ``fused=False``,
        ``HYBRIDMPM_FUSED=0`` or there is none (then :attr:`fused` is False)."""
        import onnxruntime as ort

        opts = self._options(ort, threads)
        self.fused = False
        if self._fused_asked is not False and os.environ.get("HYBRIDMPM_FUSED", "1") != "0":
            graph = _fused_bytes(self.path)
            if graph is None and self._fused_asked:
                self._not_fused = fused.why_not()  # refused by __init__ after the metadata checks
            if graph is not None:
                try:
                    fused.register(opts)
                    session = ort.InferenceSession(graph, opts, providers=["CPUExecutionProvider"])
                except Exception as e:  # noqa: BLE001 - e.g. an onnxruntime too old for the custom-op API: run the plain graph
                    if self._fused_asked:
                        raise InvalidInputError(f"fused: onnxruntime could not load the fused kernels: {e}", "fused") from e
                    warnings.warn(f"fused: running {self.path.name} without the fused edge kernels: {e}", RuntimeWarning, stacklevel=3)
                    return self._session_of(ort, str(self.path), threads)
                self.fused = True
                return session
        return self._session_of(ort, str(self.path), threads)

    def _options(self, ort: Any, threads: int) -> Any:
        """onnxruntime ``SessionOptions`` for ``threads`` intra-op threads."""
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = int(threads)
        opts.inter_op_num_threads = 1
        # by default no busy-waiting worker threads: a served model idles at 0% CPU between steps
        opts.add_session_config_entry("session.intra_op.allow_spinning", "1" if self.spinning and threads != 1 else "0")
        opts.add_session_config_entry("session.inter_op.allow_spinning", "0")
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        if self._profile:  # onnxruntime's per-node profiler (benchmarks/bench_inference.py); session.end_profiling() returns the file
            import tempfile

            opts.enable_profiling = True
            opts.profile_file_prefix = str(Path(tempfile.gettempdir()) / "hybridmpm_ort_profile")
        return opts

    def _session_of(self, ort: Any, source: str, threads: int) -> Any:
        """A plain session of the file (no custom operators)."""
        opts = self._options(ort, threads)
        try:
            return ort.InferenceSession(source, opts, providers=["CPUExecutionProvider"])
        except Exception as e:  # noqa: BLE001 - onnxruntime raises its own exception types
            raise InvalidInputError(f"model: {self.path} is not a loadable ONNX model: {e}", "model") from e

    @property
    def dim(self) -> int:
        return int(self.meta["dim"])

    @property
    def radius(self) -> float:
        return float(self.meta["radius"])

    @property
    def r_t(self) -> int:
        return int(self.meta["r_t"])

    @property
    def r_p(self) -> float:
        return float(self.meta["r_p"])

    @property
    def t_in(self) -> int:
        return int(self.meta["t_in"])

    def check_fits(self, dim: int, particle_type: np.ndarray, scene: str | None = None) -> None:
        """Raise :class:`InvalidInputError` (field ``model``) if the model cannot
        simulate particles of this dimension and these types (or this scene family)."""
        if dim != self.dim:
            raise InvalidInputError(f"model: {self.path.name} is a {self.dim}D model, the scene is {dim}D", "model")
        known = set(int(t) for t in self.meta.get("particle_types", [])) | {GNS_KINEMATIC}
        unknown = sorted(set(int(t) for t in np.unique(particle_type)) - known)
        if unknown:
            raise InvalidInputError(f"model: {self.path.name} was trained on particle types {sorted(known)}, not {unknown}", "model")
        families = self.meta.get("scenes", [self.meta.get("scene")])
        if scene is not None and families and None not in families and scene not in families:
            raise InvalidInputError(f"model: {self.path.name} was trained for {families}, not {scene!r}", "model")

    def packing(self, positions: np.ndarray, fluid: np.ndarray) -> float:
        """How densely ``positions`` float32 [N, D] are packed: the mean number of neighbours within
        R per particle of their radius graph, self-edges included, over all N particles (``fluid`` is
        not used: the graph's degree, which the network's cost follows, counts every particle)."""
        return len(radius_graph(positions, self.radius)[0]) / max(1, len(positions))

    def predict(
        self,
        history: np.ndarray,
        particle_type: np.ndarray,
        max_neighbors: int | None = None,
        graph: Graph | None = None,
    ) -> tuple[np.ndarray, np.ndarray, Graph]:
        """One step: ``history`` float32 [T_in, N, D] → ``(acceleration [N, D],
        next_position [N, D], graph)``; ``graph`` is the radius graph of
        ``history[-1]`` with self-edges as :func:`hybridmpm.graph.radius_graph`
        returns it (``senders``, ``receivers`` int64 [E], ``displacement``
        float32 [E, D], ``distance`` float32 [E]), built here unless given
        (built exactly so: the compiled graph reads the edge geometry from it).
        Raises :class:`InvalidInputError` naming ``particle_type`` for codes
        outside ``[0, NUM_TYPES)`` (onnxruntime's Gather would wrap a negative
        one) and ``graph`` for a tuple that is not those four arrays."""
        if particle_type.size and not (0 <= int(particle_type.min()) and int(particle_type.max()) < NUM_TYPES):
            raise InvalidInputError(
                f"particle_type: codes must lie in [0, {NUM_TYPES}), got {int(particle_type.min())}..{int(particle_type.max())}", "particle_type"
            )
        if graph is None:
            graph = radius_graph(history[-1], self.radius, max_neighbors=max_neighbors)
        elif len(graph) != 4:
            raise InvalidInputError(f"graph: expected (senders, receivers, displacement, distance) as radius_graph returns, got {len(graph)} arrays", "graph")
        else:
            n, r = history.shape[1], np.asarray(graph[1])
            if r.dtype != np.int64 or r.ndim != 1 or (r.size and not (0 <= int(r.min()) and int(r.max()) < n)):
                raise InvalidInputError(f"graph: receivers must be int64 [E] with values in [0, {n}) (the particles)", "graph")
        feeds = self.feeds(history, particle_type, graph)
        acc, nxt = self.session_for(feeds).run(None, feeds)
        return acc, nxt, graph

    def feeds(self, history: np.ndarray, particle_type: np.ndarray, graph: Graph) -> dict[str, np.ndarray]:
        """The inputs this graph asks for (:attr:`input_names`), from a history,
        the types and a radius graph as :meth:`predict` takes them (no checks);
        the aggregation inputs by :func:`aggregation_inputs`, for the gather way
        on more than one thread."""
        values = dict(zip(INPUT_NAMES, (history, particle_type, *graph)))
        if self.branch is not None:
            values[CONTEXT_INPUT] = self.branch.context(history, particle_type)
        if "in_edges" in self.input_names:  # the fused graph sums exactly on any thread count: no table
            values["in_edges"], values["in_degree"] = aggregation_inputs(graph[1], history.shape[1], gather=self.threads != 1 and not self.fused)
        return {name: values[name] for name in self.input_names}

    def session_for(self, feeds: dict[str, np.ndarray]) -> Any:
        """The session to run ``feeds`` (:meth:`feeds`) on: :attr:`session`, or,
        when the aggregation inputs ask for the ``ScatterND`` way on a model of
        more than one thread (a graph of very uneven in-degrees), a one-thread
        session of the same file (made on first use), where that way is exact."""
        edges = feeds.get("in_edges")
        if self.threads == 1 or self.fused or edges is None or edges.shape[1] > 0:
            return self.session
        if self._serial is None:
            self._serial = self._session(1)
        return self._serial


#: A radius graph as :func:`hybridmpm.graph.radius_graph` returns it: senders, receivers, displacement, distance.
Graph = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


__all__ = ["MAX_PADDING", "SMALL_TABLE", "Graph", "GnsRuntime", "aggregation_inputs"]
