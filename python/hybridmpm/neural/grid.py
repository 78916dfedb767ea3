"""The grid model at run time: numpy + onnxruntime + the engine's transfers (no torch).

A grid model (trained by :mod:`hybridmpm.train.grid`; a NeuralMPM-style
simulator, arXiv 2408.15753) is stored as an ONNX file holding its U-Net
alone (input ``grid`` float32 [1, C, G^D], output ``dv`` float32
[1, r_t·D, G^D]) and, in the metadata property ``hybridmpm``, ``kind:
"grid"`` with the architecture (``grid_config``) and the learned FLIP share
``beta``. One :meth:`GridRuntime.predict` is one model step of ``r_t``
frames: p2g of the history's counts and velocities
(:func:`hybridmpm._core.grid_p2g`), the U-Net, then frame-by-frame g2p and
advection (:func:`hybridmpm._core.grid_advect`) — the same arithmetic as
:meth:`hybridmpm.train.grid.GridModel.frames` (the tests hold them equal).

:class:`GridRuntime` satisfies :class:`hybridmpm.neural.base.Runtime` with
``needs_graph = False``: the simulator then builds no radius graph and
relaxes nothing, and :meth:`GridRuntime.packing` measures how densely the
particles are packed. :func:`hybridmpm.neural.base.open_model` opens a file
of this kind (its metadata's ``kind``) as a :class:`GridRuntime`.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm import _core
from hybridmpm.conventions import CONNECTIVITY_RADIUS, GNS_KINEMATIC, GNS_SAND, GNS_WATER
from hybridmpm.errors import InvalidInputError
from hybridmpm.files import check_model_file
from hybridmpm.neural.constants import METADATA_KEY
from hybridmpm.neural.grid_nodes import MASS_FLOOR, grid_geometry, wall_mask

#: ``kind`` of a grid model in its metadata (GNS files have none).
GRID_KIND = "grid"
#: The U-Net's input and output names.
GRID_INPUT, GRID_OUTPUT = "grid", "dv"


def read_metadata(session: Any, path: Path) -> dict[str, Any]:
    """The ``hybridmpm`` metadata of an onnxruntime session's model, as a dict;
    :class:`InvalidInputError` (field ``model``) if absent or not a JSON object."""
    raw = session.get_modelmeta().custom_metadata_map.get(METADATA_KEY)
    if raw is None:
        raise InvalidInputError(f"model: {path} has no '{METADATA_KEY}' metadata (not exported by hybridmpm)", "model")
    try:
        meta = json.loads(raw)
    except ValueError as e:
        raise InvalidInputError(f"model: the '{METADATA_KEY}' metadata of {path} is not JSON ({e})", "model") from e
    if not isinstance(meta, dict):
        raise InvalidInputError(f"model: the '{METADATA_KEY}' metadata of {path} is not a JSON object", "model")
    return meta


class GridRuntime:
    """An exported grid model loaded into onnxruntime (module doc).

    ``path`` an ``.onnx`` file of :func:`hybridmpm.train.grid.export_grid`;
    ``threads`` onnxruntime intra-op threads (0: one per core). Raises
    :class:`InvalidInputError` (field ``model``) for a missing file, one that
    is not a regular file (a FIFO, ``/dev/zero``) or larger than
    :data:`~hybridmpm.files.MAX_MODEL_BYTES`, another kind of model or metadata out of range; (``threads``) for a count outside
    [0, 256]."""

    needs_graph = False

    def __init__(self, path: str | Path, threads: int = 1) -> None:
        import onnxruntime as ort

        if isinstance(threads, bool) or not isinstance(threads, int) or not 0 <= threads <= 256:
            raise InvalidInputError(f"threads: must be an integer in [0, 256] (0: one per core), got {threads!r}", "threads")
        self.path = Path(path)
        check_model_file(self.path)  # a regular file of at most MAX_MODEL_BYTES (a FIFO, /dev/zero refused without blocking), before onnxruntime reads it
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = int(threads)
        opts.inter_op_num_threads = 1
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        try:
            self.session = ort.InferenceSession(str(self.path), opts, providers=["CPUExecutionProvider"])
        except Exception as e:  # noqa: BLE001 - onnxruntime raises its own exception types
            raise InvalidInputError(f"model: {self.path} is not a loadable ONNX model: {e}", "model") from e
        self.threads = threads
        meta = read_metadata(self.session, self.path)
        if meta.get("kind") != GRID_KIND:
            raise InvalidInputError(f"model: {self.path.name} is not a grid model (kind {meta.get('kind')!r})", "model")
        self.meta: dict[str, Any] = meta
        cfg: Any = meta.get("grid_config")
        try:
            self._dim = int(cfg["dim"])
            self._grid = int(cfg["grid"])
            self._r_t = int(cfg["r_t"])
            self._t_in = int(cfg["t_in"])
            self._bounds = np.asarray(cfg["bounds"], np.float32)
            self._dt = np.float32(cfg["dt_frame"])
            self._gravity = np.asarray(cfg["gravity"], np.float32)
            self._vscale = np.float32(cfg["velocity_scale"])
            self._rest = np.float32(cfg["rest_count"])
            self._materials = [t for t in (GNS_WATER, GNS_SAND) if t in [int(v) for v in cfg["types"]]]
            self._beta = np.float32(meta["beta"])
            self._pressure = float(meta["pressure_strength"]) if cfg.get("pressure") else None
        except (TypeError, KeyError, ValueError) as e:
            raise InvalidInputError(f"model.grid_config: {self.path.name} has malformed grid metadata ({e})", "model.grid_config") from e
        ok = (
            self._dim in (2, 3)
            and 8 <= self._grid <= 256
            and self._r_t >= 1
            and self._t_in >= 2
            and self._bounds.shape == (self._dim, 2)
            and bool(np.isfinite(self._bounds).all())
            and bool((self._bounds[:, 0] < self._bounds[:, 1]).all())
            and self._gravity.shape == (self._dim,)
            and all(math.isfinite(float(v)) and float(v) > 0 for v in (self._dt, self._vscale, self._rest))
            and math.isfinite(float(self._beta))
            and (self._pressure is None or (math.isfinite(self._pressure) and self._pressure >= 0))
        )
        if not ok:
            raise InvalidInputError(f"model.grid_config: {self.path.name} has grid metadata out of range", "model.grid_config")
        for key, default in (("r_t", self._r_t), ("t_in", self._t_in), ("dim", self._dim), ("r_p", 1.0)):
            self.meta.setdefault(key, default)
        self.meta.setdefault("bounds", self._bounds.tolist())
        self._origin, self._spacing = grid_geometry(self._bounds, self._grid)
        self._wall = wall_mask(self._bounds, self._grid)
        t = (self._r_t / 2 + np.arange(self._r_t, dtype=np.float32) + 0.5) * self._dt
        self._drift = (self._gravity[None, :] * t[:, None].astype(np.float32)).astype(np.float32)  # [r_t, D]

    @property
    def dim(self) -> int:
        return self._dim

    @property
    def radius(self) -> float:
        """The dataset's connectivity radius R [m] (the simulator's density and degree statistics use it)."""
        return float(self.meta.get("radius", CONNECTIVITY_RADIUS))

    @property
    def r_t(self) -> int:
        return self._r_t

    @property
    def r_p(self) -> float:
        return float(self.meta["r_p"])

    @property
    def t_in(self) -> int:
        return self._t_in

    @property
    def grid(self) -> int:
        """Grid nodes per dimension."""
        return self._grid

    def check_fits(self, dim: int, particle_type: np.ndarray, scene: str | None = None) -> None:
        """Raise :class:`InvalidInputError` (field ``model``) if the model cannot
        simulate particles of this dimension and these types (or this scene family)."""
        if dim != self.dim:
            raise InvalidInputError(f"model: {self.path.name} is a {self.dim}D model, the scene is {dim}D", "model")
        known = set(self._materials) | {GNS_KINEMATIC}
        unknown = sorted(set(int(t) for t in np.unique(particle_type)) - known)
        if unknown:
            raise InvalidInputError(f"model: {self.path.name} was trained on particle types {sorted(known)}, not {unknown}", "model")
        families = self.meta.get("scenes", [self.meta.get("scene")])
        if scene is not None and families and None not in families and scene not in families:
            raise InvalidInputError(f"model: {self.path.name} was trained for {families}, not {scene!r}", "model")

    def frames(self, history: np.ndarray, particle_type: np.ndarray) -> np.ndarray:
        """Every frame of one step: ``history`` float32 [t_in, N, D] (one step
        apart), ``particle_type`` int [N] → float32 [r_t, N, D]. Raises
        :class:`InvalidInputError` naming ``history`` for another shape or
        non-finite values."""
        h = np.asarray(history, np.float32)
        d, g = self._dim, self._grid
        if h.ndim != 3 or h.shape[0] != self._t_in or h.shape[2] != d:
            raise InvalidInputError(f"history: expected shape [{self._t_in}, N, {d}], got {list(h.shape)}", "history")
        pt = np.asarray(particle_type)
        n = h.shape[1]
        x0 = np.ascontiguousarray(h[-1])
        fluid = pt != GNS_KINEMATIC
        dt_step = np.float32(self._dt * self._r_t)
        vel = (h[1:] - h[:-1]) / dt_step  # [t_in-1, N, D]
        cols = [(pt == t).astype(np.float32)[:, None] for t in self._materials]
        cols += [(~fluid).astype(np.float32)[:, None], fluid.astype(np.float32)[:, None]]
        v_fluid = (vel * fluid[None, :, None]).transpose(1, 0, 2).reshape(n, -1)
        values = np.ascontiguousarray(np.concatenate(cols + [v_fluid], axis=1), np.float32)
        origin, spacing = self._origin.tolist(), self._spacing.tolist()
        splat = _core.grid_p2g(x0, values, origin, spacing, g)  # [G^D, M+1+1+V]
        m = len(self._materials) + 1
        mass = splat[:, m : m + 1]
        v_grid = splat[:, m + 1 :] / np.maximum(mass, np.float32(MASS_FLOOR))
        feats = np.concatenate([splat[:, :m] / self._rest, v_grid / self._vscale], axis=1)
        grid_in = np.concatenate([feats.T.reshape(1, -1, *[g] * d), self._wall], axis=1).astype(np.float32)
        (dv,) = self.session.run([GRID_OUTPUT], {GRID_INPUT: grid_in})
        dv = dv.reshape(self._r_t, d, g**d).transpose(0, 2, 1) * self._vscale  # [r_t, G^D, D]
        v_last = np.ascontiguousarray(v_grid[:, -d:], np.float32)
        velocity = np.ascontiguousarray(v_last[None] + dv, np.float32)
        own = self._beta * (vel[-1] - _core.grid_g2p(v_last, x0, origin, spacing, g))
        lo, hi = self._bounds[:, 0].tolist(), self._bounds[:, 1].tolist()
        return _core.grid_advect(  # type: ignore[no-any-return]
            x0,
            fluid,
            velocity,
            np.ascontiguousarray(own, np.float32),
            self._drift,
            float(self._dt),
            lo,
            hi,
            origin,
            spacing,
            g,
            None if self._pressure is None else (self._pressure, float(self._rest)),
        )

    def packing(self, positions: np.ndarray, fluid: np.ndarray) -> float:
        """How densely the fluid particles of ``positions`` float32 [N, D]
        (``fluid`` bool [N]) are packed: the mass-weighted mean particle count
        per grid node, ``Σ c_i² / Σ c_i`` over the nodes' p2g counts ``c_i``
        (the grid's analogue of a radius graph's mean degree)."""
        x = np.ascontiguousarray(np.asarray(positions, np.float32)[np.asarray(fluid, bool)])
        if not len(x):
            return 0.0
        c = _core.grid_p2g(x, np.ones((len(x), 1), np.float32), self._origin.tolist(), self._spacing.tolist(), self._grid)[:, 0].astype(np.float64)
        return float(c @ c / c.sum())

    def predict(
        self, history: np.ndarray, particle_type: np.ndarray, max_neighbors: int | None = None, graph: Any = None
    ) -> tuple[np.ndarray, np.ndarray, None]:
        """One step as :meth:`hybridmpm.neural.runtime.GnsRuntime.predict` returns
        it: ``(acceleration [N, D] in m per step², next_position [N, D], None)``
        (no graph; ``max_neighbors`` and ``graph`` are ignored)."""
        nxt = self.frames(history, particle_type)[-1]
        h = np.asarray(history, np.float32)
        return nxt - 2 * h[-1] + h[-2], nxt, None


__all__ = ["GRID_INPUT", "GRID_KIND", "GRID_OUTPUT", "MASS_FLOOR", "GridRuntime", "grid_geometry", "read_metadata", "wall_mask"]
