"""The learned correction at run time: a per-particle MLP on
:func:`~experiments.learned_correction.features.particle_features`, in numpy (no torch).

``Correction.velocity_change(features)`` returns the change of velocity
[cells per frame] the fine grid would have made that the coarse grid does not;
:meth:`Correction.acceleration` turns it into the per-particle acceleration
[m/s²] the coarse solver applies through its forcing path during the next
frame (``Δv/Δt``: a force inside the solver, INC, arXiv 2511.12764, not an
overwrite of the state).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hybridmpm.errors import InvalidInputError
from hybridmpm.files import loads_json


@dataclass
class Correction:
    """Weights of an MLP ``F → H → … → D`` with SiLU between layers; inputs
    standardised with ``x_mean``/``x_std`` [F], outputs scaled by ``y_std``
    [D] (cells per frame). ``meta`` records the scene, the coarse grid and the
    training that made it."""

    weights: list[np.ndarray]
    biases: list[np.ndarray]
    x_mean: np.ndarray
    x_std: np.ndarray
    y_std: np.ndarray
    meta: dict

    def velocity_change(self, features: np.ndarray) -> np.ndarray:
        """``features`` float32 [N, F] → Δv float32 [N, D] [cells per frame]."""
        h = (np.asarray(features, np.float32) - self.x_mean) / self.x_std
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            h = h @ w + b
            if i < last:
                h = h * (0.5 + 0.5 * np.tanh(0.5 * h))  # SiLU, h·sigmoid(h) without overflow
        return (h * self.y_std).astype(np.float32)

    def acceleration(self, features: np.ndarray, n_grid: int, dt_frame: float) -> np.ndarray:
        """The acceleration [m/s²] float32 [N, D] that adds the predicted Δv over one frame of ``dt_frame`` [s]
        on a grid of ``n_grid`` cells."""
        return (self.velocity_change(features) * (1.0 / n_grid) / dt_frame / dt_frame).astype(np.float32)

    def save(self, path: str | Path) -> None:
        """Write the weights, normalisation and ``meta`` (as JSON) to an ``.npz`` file."""
        arrays: dict[str, np.ndarray] = {f"w{i}": w for i, w in enumerate(self.weights)} | {f"b{i}": b for i, b in enumerate(self.biases)}
        arrays |= {"x_mean": self.x_mean, "x_std": self.x_std, "y_std": self.y_std, "meta": np.array(json.dumps(self.meta))}
        np.savez(path, **arrays)  # type: ignore[arg-type]

    @classmethod
    def load(cls, path: str | Path) -> Correction:
        """Read a :meth:`save` file; raises :class:`InvalidInputError` naming ``model`` if it is not one."""
        try:
            with np.load(path, allow_pickle=False) as z:
                n = sum(1 for k in z.files if k.startswith("w"))
                return cls(
                    [z[f"w{i}"].astype(np.float32) for i in range(n)],
                    [z[f"b{i}"].astype(np.float32) for i in range(n)],
                    z["x_mean"].astype(np.float32),
                    z["x_std"].astype(np.float32),
                    z["y_std"].astype(np.float32),
                    loads_json(str(z["meta"]), "model"),  # nesting checked before parsing
                )
        except (OSError, KeyError, ValueError) as e:
            raise InvalidInputError(f"model: {path} is not a correction model ({e})", "model") from e


__all__ = ["Correction"]
