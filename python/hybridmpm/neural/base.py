"""The socket of the learned simulators: what every learned kind offers at run time, and the one way to open one.

A *kind* of learned simulator (the GNS, :class:`~hybridmpm.neural.runtime.GnsRuntime`, with or without
its grid branch; the grid model, :class:`~hybridmpm.neural.grid.GridRuntime`) is stored as an ONNX file
whose ``hybridmpm`` metadata says what it is (``kind``; a GNS has none). Whatever the kind, the
simulators (:class:`hybridmpm.sim.NeuralSimulator`, the hybrid), the bench and tune call only what
:class:`Runtime` declares, and they open a file only through :func:`open_model`. A new kind is one
module with one class that satisfies :class:`Runtime`, and one line in :data:`KINDS`.

:func:`read_header` reads a model file's metadata without loading the model (no onnxruntime session):
what the hybrid's classical twin needs of the network whose particles it carries (``r_p``, ``r_t``,
``T_in``).

Paper Sec. 2.2, 3.1.1 (``r_p``, ``r_t``, ``T_in``) and App. A.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from hybridmpm.conventions import T_IN
from hybridmpm.errors import InvalidInputError
from hybridmpm.files import loads_json, read_model_file
from hybridmpm.models import shipped_model
from hybridmpm.neural.constants import METADATA_KEY
from hybridmpm.neural.grid import GRID_KIND, GridRuntime
from hybridmpm.neural.runtime import GnsRuntime, Graph

#: The kind of a GNS file (its metadata names no kind).
GNS_KIND = "gns"
#: Each learned kind's run-time class, by the ``kind`` its file's metadata holds (:data:`GNS_KIND` when absent).
KINDS: dict[str, type] = {GNS_KIND: GnsRuntime, GRID_KIND: GridRuntime}


@runtime_checkable
class Runtime(Protocol):
    """A learned simulator at run time: what the simulators, ``hybridmpm bench`` and ``tune`` call.

    Attributes: ``path`` the ONNX file; ``meta`` its ``hybridmpm`` metadata (``scene``, ``dim``,
    ``radius``, ``r_p``, ``r_t``, ``t_in``, errors, parameter count ...); ``needs_graph`` whether
    its input is a radius graph of the particles (a GNS: the simulator builds the graph, relaxes the
    density between steps and measures packing as the graph's mean degree) or not (a grid model: it
    moves the particles through its own grid, and :meth:`packing` measures their packing).
    """

    path: Path
    meta: dict[str, Any]
    needs_graph: bool

    @property
    def dim(self) -> int:
        """2 or 3."""
        ...

    @property
    def radius(self) -> float:
        """The connectivity radius R [m] of its data set (the simulators' neighbour statistics use it)."""
        ...

    @property
    def r_p(self) -> float:
        """Spatial downsampling in (0, 1]: the particle set it runs on (paper Sec. 3.1.1)."""
        ...

    @property
    def r_t(self) -> int:
        """Frames per model step (temporal downsampling, paper Sec. 3.1.1)."""
        ...

    @property
    def t_in(self) -> int:
        """Positions it reads per step (the current one and ``t_in − 1`` before it): its input."""
        ...

    def check_fits(self, dim: int, particle_type: np.ndarray, scene: str | None = None) -> None:
        """Raise :class:`~hybridmpm.errors.InvalidInputError` (field ``model``) for particles of another
        dimension, of types it was not trained on, or a scene family it was not trained for."""
        ...

    def predict(
        self, history: np.ndarray, particle_type: np.ndarray, max_neighbors: int | None = None, graph: Graph | None = None
    ) -> tuple[np.ndarray, np.ndarray, Graph | None]:
        """One model step: ``history`` float32 [t_in, N, D] (one step apart), ``particle_type`` int64 [N]
        → ``(acceleration [N, D] in m per step², next positions [N, D], the radius graph it used or None)``."""
        ...

    def packing(self, positions: np.ndarray, fluid: np.ndarray) -> float:
        """How densely the fluid particles (``fluid`` bool [N]) of ``positions`` float32 [N, D] are
        packed, in the kind's own unit (the failure check "compressed" compares it with the initial
        condition's)."""
        ...


@dataclass(frozen=True)
class ModelHeader:
    """A model file's resolution, read from its metadata without loading it (:func:`read_header`).

    ``path`` the file; ``kind`` its kind (a key of :data:`KINDS`); ``meta`` the whole ``hybridmpm``
    metadata; ``r_p`` in (0, 1], ``r_t`` frames per step and ``t_in`` positions per input, as the
    model's :class:`Runtime` would report them."""

    path: Path
    kind: str
    meta: dict[str, Any]
    r_p: float
    r_t: int
    t_in: int


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        b = buf[i]
        i += 1
        value |= (b & 0x7F) << shift
        if not b & 0x80:
            return value, i
        shift += 7


def _fields(buf: bytes) -> Iterator[tuple[int, Any]]:
    """The top-level fields of a protocol-buffer message: (field number, value) with length-delimited values as bytes."""
    i = 0
    while i < len(buf):
        key, i = _varint(buf, i)
        number, wire = key >> 3, key & 7
        value: Any
        if wire == 0:
            value, i = _varint(buf, i)
        elif wire in (1, 5):
            size = 8 if wire == 1 else 4
            value, i = buf[i : i + size], i + size
        elif wire == 2:
            size, i = _varint(buf, i)
            value, i = buf[i : i + size], i + size
        else:
            raise ValueError(f"wire type {wire}")
        if i > len(buf):
            raise ValueError("truncated")
        yield number, value


#: ``ModelProto.metadata_props`` and the key and value of its ``StringStringEntryProto`` (onnx.proto).
_METADATA_PROPS, _KEY, _VALUE = 14, 1, 2


def metadata_of(buf: bytes) -> dict[str, Any] | None:
    """The ``hybridmpm`` metadata of the serialised ONNX model ``buf`` as a dict, read from its
    top-level ``metadata_props`` (the protocol-buffer wire format; no onnxruntime session), or None
    when ``buf`` is not a readable ONNX model or holds no such metadata as a JSON object."""
    try:
        for number, value in _fields(buf):
            if number != _METADATA_PROPS:
                continue
            entry = dict(_fields(value))
            if bytes(entry.get(_KEY, b"")) == METADATA_KEY.encode():
                meta = loads_json(bytes(entry.get(_VALUE, b"")), "model")  # nesting checked: a deep one is unreadable (None)
                return meta if isinstance(meta, dict) else None
    except (ValueError, IndexError, UnicodeDecodeError):
        return None
    return None


def file_metadata(path: str | Path) -> dict[str, Any] | None:
    """The ``hybridmpm`` metadata of the ONNX file ``path`` (:func:`metadata_of` of its bytes), or
    None when the file is not a readable ONNX model or holds no such metadata as a JSON object.
    The file is read by :func:`hybridmpm.files.read_model_file`: raises :class:`InvalidInputError` (field ``model``)
    for a path that is missing, not a regular file (a FIFO, ``/dev/zero``) or larger than
    :data:`~hybridmpm.files.MAX_MODEL_BYTES`."""
    return metadata_of(read_model_file(path))


def _kind_of(meta: dict[str, Any] | None) -> str:
    kind = (meta or {}).get("kind")
    return kind if isinstance(kind, str) and kind in KINDS else GNS_KIND


def model_kind(path: str | Path) -> str:
    """The kind of the model file at ``path``: its metadata's ``kind`` where :data:`KINDS` knows it,
    else :data:`GNS_KIND` (a GNS has none; a file that is no ONNX model is left to the GNS loader to
    refuse). Raises :class:`InvalidInputError` (field ``model``) as :func:`hybridmpm.files.read_model_file` does."""
    return _kind_of(file_metadata(path))


def read_header(model: Runtime | ModelHeader | str | Path | None, scene: str | None = None) -> ModelHeader:
    """The resolution of ``model`` (a run-time model, a header, an ``.onnx`` path, or None for the shipped
    model of ``scene``) without loading it. Raises :class:`InvalidInputError` (field ``model``) for a
    file that is missing, not a regular file (a FIFO, a device such as ``/dev/zero``), larger than
    :data:`~hybridmpm.files.MAX_MODEL_BYTES` or without ``hybridmpm`` metadata, ``model.<key>`` for ``r_p`` outside (0, 1],
    ``r_t`` or ``t_in`` not an integer >= 1 (>= 3)."""
    if isinstance(model, ModelHeader):
        return model
    if model is not None and not isinstance(model, (str, Path)):
        return ModelHeader(Path(model.path), model_kind(model.path), dict(model.meta), float(model.r_p), int(model.r_t), int(model.t_in))
    path = Path(_resolve(model, scene))
    meta = metadata_of(read_model_file(path))
    if meta is None:
        raise InvalidInputError(f"model: {path} has no '{METADATA_KEY}' metadata (not an ONNX model exported by hybridmpm)", "model")
    kind = _kind_of(meta)
    grid = meta.get("grid_config")
    source: dict[str, Any] = grid if kind == GRID_KIND and isinstance(grid, dict) else meta
    r_p, r_t, t_in = meta.get("r_p", 1.0), source.get("r_t", 1), source.get("t_in", T_IN)
    if isinstance(r_p, bool) or not isinstance(r_p, (int, float)) or not (math.isfinite(r_p) and 0 < r_p <= 1):
        raise InvalidInputError(f"model.r_p: {path.name} has r_p = {r_p!r}, expected a number in (0, 1]", "model.r_p")
    for key, value, lo in (("r_t", r_t, 1), ("t_in", t_in, 3)):
        if isinstance(value, bool) or not isinstance(value, int) or value < lo:
            raise InvalidInputError(f"model.{key}: {path.name} has {key} = {value!r}, expected an integer >= {lo}", f"model.{key}")
    return ModelHeader(path, kind, meta, float(r_p), int(r_t), int(t_in))


def _resolve(model: str | Path | None, scene: str | None) -> str | Path:
    if model is not None:
        return model
    if scene is None:
        raise InvalidInputError("model: no model given and the scene has no name to find a shipped one", "model")
    return shipped_model(scene)


def open_model(model: Runtime | str | Path | None, scene: str | None = None, threads: int = 1) -> Runtime:
    """``model`` as a run-time model, whatever its kind: itself when it is one already, the ``.onnx``
    file at a path opened by its kind's class (:data:`KINDS`, chosen by :func:`model_kind`), or (None)
    the shipped model of ``scene``. ``threads`` onnxruntime intra-op threads (0: one per core).
    Raises :class:`InvalidInputError`: field ``nn_threads`` for ``threads`` outside [0, 256],
    ``model`` for no model and no scene name, a file that is missing, not a regular file (a FIFO, a
    device such as ``/dev/zero``) or larger than :data:`~hybridmpm.files.MAX_MODEL_BYTES`,
    and as the kind's class does (a missing or foreign file,
    metadata out of range)."""
    if isinstance(threads, bool) or not isinstance(threads, int) or not 0 <= threads <= 256:
        raise InvalidInputError(f"nn_threads: must be an integer in [0, 256], got {threads!r}", "nn_threads")
    if model is not None and not isinstance(model, (str, Path)):
        return model
    path = _resolve(model, scene)
    runtime: Runtime = KINDS[model_kind(path)](path, threads=threads)  # model_kind reads the file: refuses a FIFO, a device, a huge file
    return runtime


__all__ = ["GNS_KIND", "KINDS", "ModelHeader", "Runtime", "file_metadata", "metadata_of", "model_kind", "open_model", "read_header"]
