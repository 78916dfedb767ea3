"""The GNS's grid branch at run time: numpy + onnxruntime + the engine's transfers (no torch).

A GNS trained with a grid branch (:mod:`hybridmpm.train.gns.grid_branch`)
is stored as one ``.onnx`` file: its inference graph takes one more input,
``grid_context`` float32 [N, latent], added to the node latents after the
encoder; its metadata (``grid_branch``) holds the branch's constants and
its U-Net as a second ONNX graph (base64, input ``grid`` float32
[1, C, G^D...], output ``context`` float32 [1, latent, G^D...]).
:class:`GridBranchRuntime` computes ``grid_context`` for a position history:
p2g of the counts and normalised velocities (:func:`hybridmpm._core.grid_p2g`,
the quadratic B-spline of MLS-MPM), the U-Net, g2p of its channels
(:func:`hybridmpm._core.grid_g2p`) — the arithmetic of
:meth:`hybridmpm.train.gns.grid_branch.GridBranch.forward` (the tests hold
them equal).
"""

from __future__ import annotations

import base64
import math
from typing import Any

import numpy as np

from hybridmpm import _core
from hybridmpm.conventions import GNS_KINEMATIC
from hybridmpm.errors import InvalidInputError
from hybridmpm.neural.constants import BRANCH_KEY, CONTEXT_INPUT
from hybridmpm.neural.grid_nodes import MASS_FLOOR, grid_geometry, wall_mask

#: The branch U-Net's input and output names.
BRANCH_INPUT, BRANCH_OUTPUT = "grid", "context"


def branch_channels(dim: int, fluid_types: int, t_in: int) -> int:
    """Input channels of the branch's U-Net: a count per fluid type and one
    for the obstacles, ``(t_in − 1)·dim`` mean velocities, the wall mask."""
    return fluid_types + 1 + (t_in - 1) * dim + 1


class GridBranchRuntime:
    """The branch of a GNS file (module doc) in onnxruntime on ``threads``
    intra-op threads. ``spec`` is the metadata's ``grid_branch`` object
    (``grid``, ``types``, ``rest_count``, ``vel_mean``, ``vel_std``,
    ``latent``, ``onnx``); ``meta`` the file's metadata (``dim``, ``bounds``,
    ``t_in``). Raises :class:`InvalidInputError` naming ``model.grid_branch``
    for a spec that is not one."""

    def __init__(self, spec: Any, meta: dict[str, Any], threads: int = 1) -> None:
        import onnxruntime as ort

        def bad(what: str) -> InvalidInputError:
            return InvalidInputError(f"model.{BRANCH_KEY}: {what}", f"model.{BRANCH_KEY}")

        if not isinstance(spec, dict):
            raise bad("expected a JSON object")
        d, t_in = int(meta["dim"]), int(meta["t_in"])
        try:
            self.grid = int(spec["grid"])
            self.types = [int(t) for t in spec["types"]]
            self.rest = float(spec["rest_count"])
            self.vel_mean = np.tile(np.asarray(spec["vel_mean"], np.float32), t_in - 1)
            self.vel_std = np.tile(np.asarray(spec["vel_std"], np.float32), t_in - 1)
            self.latent = int(spec["latent"])
            graph = base64.b64decode(spec["onnx"], validate=True)
        except (KeyError, TypeError, ValueError) as e:
            raise bad(f"missing or malformed entry ({e})") from None
        if not (self.grid >= 8 and math.isfinite(self.rest) and self.rest > 0 and self.vel_mean.shape == ((t_in - 1) * d,)):
            raise bad(f"grid {self.grid} (>= 8), rest_count {self.rest} (> 0) or velocity statistics of length {d} out of range")
        if not (np.isfinite(self.vel_std).all() and (self.vel_std > 0).all() and np.isfinite(self.vel_mean).all()):
            raise bad("velocity statistics must be finite, the stds > 0")
        self.dim, self.t_in = d, t_in
        bounds = np.asarray(meta["bounds"], np.float64)
        self._lo, self._hi = bounds[:, 0].astype(np.float32), bounds[:, 1].astype(np.float32)
        origin, spacing = grid_geometry(bounds, self.grid)
        self._origin, self._spacing = origin.tolist(), spacing.tolist()
        self._wall = wall_mask(bounds, self.grid)
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = int(threads)
        opts.inter_op_num_threads = 1
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        try:
            self.session = ort.InferenceSession(graph, opts, providers=["CPUExecutionProvider"])
        except Exception as e:  # noqa: BLE001 - onnxruntime raises its own exception types
            raise bad(f"its U-Net is not a loadable ONNX graph: {e}") from None

    def context(self, history: np.ndarray, particle_type: np.ndarray) -> np.ndarray:
        """``grid_context`` float32 [N, latent] for a history float32
        [t_in, N, D] (one model step apart, metres) and types int [N]."""
        h = np.asarray(history, np.float32)
        pt = np.asarray(particle_type)
        n, d, g = h.shape[1], self.dim, self.grid
        x = np.ascontiguousarray(np.clip(h[-1], self._lo, self._hi), np.float32)
        vel = ((h[1:] - h[:-1]).transpose(1, 0, 2).reshape(n, (h.shape[0] - 1) * d) - self.vel_mean) / self.vel_std  # [N, (t_in-1)·D]; N may be 0
        fluid = (pt != GNS_KINEMATIC).astype(np.float32)[:, None]
        cols = [(pt == t).astype(np.float32)[:, None] for t in self.types] + [1.0 - fluid, fluid, vel * fluid]
        values = np.ascontiguousarray(np.concatenate(cols, axis=1), np.float32)
        splat = _core.grid_p2g(x, values, self._origin, self._spacing, g)  # [G^D, C - 1]
        m = len(self.types) + 1
        mass = splat[:, m : m + 1]
        feats = np.concatenate([splat[:, :m] / np.float32(self.rest), splat[:, m + 1 :] / np.maximum(mass, np.float32(MASS_FLOOR))], axis=1)
        grid_in = np.concatenate([feats.T.reshape(1, -1, *[g] * d), self._wall], axis=1).astype(np.float32)
        (out,) = self.session.run([BRANCH_OUTPUT], {BRANCH_INPUT: grid_in})
        field = np.ascontiguousarray(out.reshape(self.latent, -1).T, np.float32)  # [G^D, latent]
        return _core.grid_g2p(field, x, self._origin, self._spacing, g)  # type: ignore[no-any-return]


__all__ = ["BRANCH_INPUT", "BRANCH_KEY", "BRANCH_OUTPUT", "CONTEXT_INPUT", "GridBranchRuntime", "branch_channels"]
