"""The network at run time: numpy + onnxruntime (no torch).

:class:`NeuralModel` wraps an exported GNS (see :mod:`hybridmpm.neural.export`)
and its metadata, and predicts one model step (``r_t`` frames) from a position
history (paper Sec. 2.2, App. A). The simulator that rolls it out is
:class:`hybridmpm.sim.NeuralSimulator`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.conventions import GNS_KINEMATIC, T_IN
from hybridmpm.errors import InvalidInputError
from hybridmpm.graph import radius_graph
from hybridmpm.neural.constants import FEATURE_VERSION, METADATA_KEY


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
        return int(self.meta.get("t_in", T_IN))

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
        acc, nxt = self.session.run(None, {"positions": history, "particle_type": particle_type, "senders": s, "receivers": r})
        return acc, nxt, (s, r)


__all__ = ["NeuralModel"]
