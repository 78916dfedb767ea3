"""The neural simulator at run time: numpy + onnxruntime (no torch).

:class:`NeuralModel` wraps an exported GNS (see :mod:`hybridmpm.neural.export`)
and its metadata; :class:`NeuralSimulator` keeps the position history, builds
the radius graph with the Rust cell list each step, runs onnxruntime and
returns the next positions (paper Sec. 2.2, App. A). One neural step advances
``r_t`` frames of ``dt_frame``.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError
from hybridmpm.graph import radius_graph
from hybridmpm.neural.constants import FEATURE_VERSION, KINEMATIC, METADATA_KEY


class NeuralModel:
    """An exported GNS model loaded into onnxruntime.

    ``path`` an ``.onnx`` file written by :func:`~hybridmpm.neural.export.export_onnx`;
    ``threads`` onnxruntime intra-op threads (1 is as fast as 2 for small nets
    and leaves a core to MPM). ``meta`` holds the model's metadata: ``scene``,
    ``dim``, ``radius`` R [m], ``r_p``, ``r_t``, ``t_in``, ``particle_types``,
    ``feature_version``, ``data_sha256``, architecture and errors.
    Raises :class:`InvalidInputError` (field ``model``) for a missing or
    foreign file or an incompatible feature version.
    """

    def __init__(self, path: str | Path, threads: int = 1) -> None:
        import onnxruntime as ort

        self.path = Path(path)
        if not self.path.is_file():
            raise InvalidInputError(f"model: no such file {self.path}", "model")
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = int(threads)
        opts.inter_op_num_threads = 1
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        try:
            self.session = ort.InferenceSession(str(self.path), opts, providers=["CPUExecutionProvider"])
        except Exception as e:  # noqa: BLE001 - onnxruntime raises its own exception types
            raise InvalidInputError(f"model: {self.path} is not a loadable ONNX model: {e}", "model") from e
        raw = self.session.get_modelmeta().custom_metadata_map.get(METADATA_KEY)
        if raw is None:
            raise InvalidInputError(f"model: {self.path} has no '{METADATA_KEY}' metadata (not exported by hybridmpm)", "model")
        self.meta: dict[str, Any] = json.loads(raw)
        if self.meta.get("feature_version") != FEATURE_VERSION:
            raise InvalidInputError(
                f"model: feature version {self.meta.get('feature_version')} of {self.path} is not {FEATURE_VERSION} (this hybridmpm)", "model"
            )

    @property
    def dim(self) -> int:
        return int(self.meta["dim"])

    @property
    def radius(self) -> float:
        return float(self.meta["radius"])

    @property
    def r_t(self) -> int:
        return int(self.meta.get("r_t", 1))

    @property
    def r_p(self) -> float:
        return float(self.meta.get("r_p", 1.0))

    @property
    def t_in(self) -> int:
        return int(self.meta.get("t_in", 6))

    def check_fits(self, dim: int, particle_type: np.ndarray, scene: str | None = None) -> None:
        """Raise :class:`InvalidInputError` (field ``model``) if the model cannot
        simulate particles of this dimension and these types (or this scene family)."""
        if dim != self.dim:
            raise InvalidInputError(f"model: {self.path.name} is a {self.dim}D model, the scene is {dim}D", "model")
        known = set(int(t) for t in self.meta.get("particle_types", [])) | {KINEMATIC}
        unknown = sorted(set(int(t) for t in np.unique(particle_type)) - known)
        if unknown:
            raise InvalidInputError(f"model: {self.path.name} was trained on particle types {sorted(known)}, not {unknown}", "model")
        families = self.meta.get("scenes", [self.meta.get("scene")])
        if scene is not None and families and None not in families and scene not in families:
            raise InvalidInputError(f"model: {self.path.name} was trained for {families}, not {scene!r}", "model")

    def predict(
        self,
        history: np.ndarray,
        particle_type: np.ndarray,
        max_neighbors: int | None = None,
        graph: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """One step: ``history`` float32 [T_in, N, D] → ``(acceleration [N, D],
        next_position [N, D], (senders, receivers))``; the graph is built on
        ``history[-1]`` with self-edges, unless ``graph`` (senders, receivers
        int64 [E], built exactly so) is given."""
        if graph is None:
            s, r, _, _ = radius_graph(history[-1], self.radius, max_neighbors=max_neighbors)
        else:
            s, r = graph
        acc, nxt = self.session.run(
            None, {"positions": history, "particle_type": particle_type, "senders": s, "receivers": r}
        )
        return acc, nxt, (s, r)


class NeuralSimulator:
    """Roll out a GNS model from a position history.

    ``model`` a :class:`NeuralModel` or a path; ``history`` float [T_in, N, D]
    (oldest first, ``r_t`` frames apart, metres); ``particle_type`` int [N].
    :meth:`step` advances one model step (``r_t`` frames) and returns float32
    positions [N, D]. With ``clamp`` (default) predicted positions are clipped
    to the model's domain ``bounds`` (the walls, which the network only sees
    through its wall-distance features); ``last_clamped`` counts the
    particles clipped in the last step (a sign of a failing model). Raises :class:`InvalidInputError` for shapes, NaN, or a
    model that does not fit.
    """

    def __init__(
        self,
        model: NeuralModel | str | Path,
        history: np.ndarray,
        particle_type: np.ndarray,
        *,
        scene: str | None = None,
        max_neighbors: int | None = None,
        clamp: bool = True,
    ) -> None:
        self.model = model if isinstance(model, NeuralModel) else NeuralModel(model)
        h = np.asarray(history, dtype=np.float32)
        t_in = self.model.t_in
        if h.ndim != 3 or h.shape[0] != t_in or h.shape[2] not in (2, 3):
            raise InvalidInputError(f"history: expected shape [{t_in}, N, D], got {h.shape}", "history")
        if not np.all(np.isfinite(h)):
            raise InvalidInputError("history: contains NaN or inf", "history")
        pt = np.asarray(particle_type)
        if pt.shape != (h.shape[1],) or not np.issubdtype(pt.dtype, np.integer):
            raise InvalidInputError(f"particle_type: expected {h.shape[1]} integers, got shape {pt.shape}", "particle_type")
        self.model.check_fits(h.shape[2], pt, scene)
        self.history = h.copy()
        self.particle_type = pt.astype(np.int64)
        self.max_neighbors = max_neighbors
        self.clamp = clamp
        b = np.asarray(self.model.meta["bounds"], np.float32)
        self._lo, self._hi = b[:, 0], b[:, 1]
        self.steps = 0
        self.last_edges = 0
        self.last_clamped = 0

    @property
    def positions(self) -> np.ndarray:
        """Current positions, float32 [N, D]."""
        return self.history[-1]

    def step(self) -> np.ndarray:
        """Advance one model step (``r_t`` frames); returns float32 [N, D]."""
        _, nxt, (s, _) = self.model.predict(self.history, self.particle_type, self.max_neighbors)
        self.last_edges = int(len(s))
        return self.accept(nxt)

    def accept(self, nxt: np.ndarray) -> np.ndarray:
        """Append predicted positions ``nxt`` [N, D] to the history, clipped
        to the domain if ``clamp`` (:meth:`clip` then :meth:`push`); returns
        them as float32 [N, D]. :meth:`step` is ``model.predict`` then ``accept``."""
        return self.push(self.clip(nxt))

    def clip(self, nxt: np.ndarray) -> np.ndarray:
        """``nxt`` [N, D] clipped to the model's domain bounds if ``clamp``
        (``last_clamped`` counts the particles clipped)."""
        if self.clamp:
            out = (nxt < self._lo) | (nxt > self._hi)
            self.last_clamped = int(out.any(axis=1).sum())
            if self.last_clamped:
                nxt = np.clip(nxt, self._lo, self._hi)
        return nxt

    def push(self, positions: np.ndarray) -> np.ndarray:
        """Append ``positions`` [N, D] to the history as they are; returns them as float32."""
        self.history = np.concatenate([self.history[1:], positions[None].astype(np.float32)])
        self.steps += 1
        return self.history[-1]

    def rollout(self, steps: int) -> np.ndarray:
        """``steps`` steps; returns float32 [steps + 1, N, D] starting with the current positions."""
        out = [self.positions.copy()]
        for _ in range(int(steps)):
            out.append(self.step().copy())
        return np.stack(out)


def warmup_frames(model: NeuralModel) -> int:
    """MPM frames needed before the first neural step: ``(T_in − 1)·r_t``."""
    return (model.t_in - 1) * model.r_t




def run_neural(
    scene: Any,
    model: NeuralModel,
    frames: int,
    *,
    seed: int = 0,
    mpm_threads: int = 0,
    progress: bool = False,
) -> dict[str, Any]:
    """Roll out ``model`` from a scene's initial condition (``hybridmpm simulate --solver neural``).

    The scene is downsampled to the model's ``r_p`` (k-means seeded by ``seed``),
    MPM runs the first ``(T_in − 1)·r_t`` frames to fill the position history,
    then the network advances ``r_t`` frames a step up to ``frames``. Returns
    ``positions`` float32 [K + 1, N + B, D] every ``r_t`` frames (boundary
    particles appended), ``particle_type`` [N + B], ``masses`` [N], ``scene``
    (the low-resolution scene), ``dt_stored`` [s], ``step_seconds`` float64
    [steps] (graph build + inference per neural step), ``warmup_frames``,
    ``edges`` (mean edges per step). Raises :class:`InvalidInputError` if the
    model does not fit the scene.
    """
    from tqdm import tqdm

    from hybridmpm.data.resolution import downsample_scene

    low = downsample_scene(scene, model.r_p, seed=seed).scene if model.r_p < 1.0 else scene
    ptype = low.particle_type()
    model.check_fits(low.dim, ptype, getattr(scene, "name", None))
    r_t = model.r_t
    sim = low.make_solver(num_threads=mpm_threads)
    hist = [low.with_boundary(sim.positions)]
    for f in range(1, warmup_frames(model) + 1):
        sim.step_frame(low.dt_frame)
        if f % r_t == 0:
            hist.append(low.with_boundary(sim.positions))
    neural = NeuralSimulator(model, np.stack(hist), ptype, scene=getattr(scene, "name", None))
    steps = max(0, math.ceil((frames - warmup_frames(model)) / r_t))
    out = list(hist)
    times = np.empty(steps)
    edges = 0
    for k in tqdm(range(steps), desc=f"{getattr(scene, 'name', 'scene')} [neural]", unit="step", disable=not progress):
        t0 = time.perf_counter()
        out.append(neural.step().copy())
        times[k] = time.perf_counter() - t0
        edges += neural.last_edges
    return {
        "positions": np.stack(out),
        "particle_type": ptype,
        "masses": np.asarray(sim.masses, np.float32),
        "material": np.asarray(low.material, np.int32),
        "scene": low,
        "dt_stored": low.dt_frame * r_t,
        "step_seconds": times,
        "warmup_frames": warmup_frames(model),
        "edges": edges / max(steps, 1),
    }


__all__ = ["NeuralModel", "NeuralSimulator", "run_neural", "warmup_frames"]
