"""The hybrid simulator: neural physics by default, MPM when the flow gets complex.

Paper Sec. 3.1.2, Eq. 1, Table 2; DESIGN.md "Safeguard". One *step* is one
coarse step of the neural model: ``r_t`` frames of ``dt_frame`` seconds, at the
model's particle resolution ``r_p`` (the scene is clustered once; MPM and the
network move the same particles).

Control (``r_c`` threshold, ``δ`` window, ``dwell``):

* the first ``T_in − 1`` steps are MPM (they fill the network's history);
* on the neural solver, a step whose score ``s(t) < r_c`` hands the next
  step to MPM (neural → MPM conversion, :mod:`hybridmpm.hybrid.convert`);
* on MPM, the score keeps being computed on the MPM trajectory; after
  ``dwell`` consecutive steps with ``s(t) ≥ r_c`` the network takes over
  again from the last ``T_in`` positions;
* ``r_c ≤ 0`` switches the complexity trigger off (neural only, as the
  paper's Table 2 reads r_c = 0; the mean cosine can dip below 0 in a splash);
  ``r_c > 1`` can never be met: MPM only.

Failure handling (always on, whatever ``r_c``): a neural step that predicts a
non-finite position, moves a particle more than ``escape_cells`` cells (default
4) beyond the model's domain bounds (a working water2d model overshoots the
walls by at most 2.7 cells before clipping: 3 seeds × 1000 frames), raises the
kinetic energy above ``ke_factor`` × the energy available at the start
(kinetic + potential above the floor), or packs the particles so that their
mean number of neighbours within R exceeds ``degree_factor`` (2) × that of the
initial condition (sand and water are nearly incompressible: a collapsing
network shows there first, and its graph, hence its cost, grows with it) is
discarded, and the step is redone by MPM from the last good state
(``Frame.event`` says which). The network then has to wait ``dwell·2^k``
calm steps, ``k`` its failures since its last healthy stint of ``2·dwell``
steps (backoff: a model that keeps collapsing is not handed the flow every
few steps). MPM itself halves its substep and retries a frame that goes
non-finite or violates the CFL condition (Rust ``step_frame``).
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from hybridmpm.errors import InvalidInputError
from hybridmpm.graph import radius_graph
from hybridmpm.hybrid.convert import mpm_history, neural_to_mpm
from hybridmpm.hybrid.safeguard import ACCEL_FLOOR, DELTA, R_C, complexity_score
from hybridmpm.mpm import MpmSolver
from hybridmpm.neural.runtime import NeuralModel, NeuralSimulator
from hybridmpm.scenes.core import Scene

#: Default dwell (steps of s ≥ r_c on MPM before the network takes over again);
#: see docs/hybrid.md for the measurement behind it.
DWELL = 5
#: After a failure fallback the dwell doubles per failure since the network's
#: last healthy stint (2·dwell steps without failure), up to 2**MAX_BACKOFF.
MAX_BACKOFF = 6
#: Solver tags.
MPM = "mpm"
NEURAL = "neural"


@dataclass
class Frame:
    """One step of the hybrid simulator.

    ``step`` coarse step index (0 = initial condition), ``frame`` frame number
    (``step·r_t``), ``time`` [s]; ``positions`` float32 [N + B, D] [m] (fluid,
    then static boundary particles); ``solver`` "mpm" or "neural" (the one that
    produced these positions); ``seconds`` wall time of the step (solver,
    conversion and safeguard); ``score`` s(t) after the step (nan while
    undefined); ``event`` None or what happened: "switch:mpm",
    "switch:neural", "fallback:nan", "fallback:escaped", "fallback:energy", "fallback:compressed";
    ``mpm_retries`` substep halvings MPM needed in this step.
    """

    step: int
    frame: int
    time: float
    positions: np.ndarray
    solver: str
    seconds: float
    score: float
    event: str | None = None
    mpm_retries: int = 0


@dataclass
class HybridStats:
    """Counters of a hybrid run."""

    steps: dict[str, int] = field(default_factory=lambda: {MPM: 0, NEURAL: 0})
    switches: int = 0
    fallbacks: dict[str, int] = field(default_factory=dict)
    mpm_retries: int = 0


def _check(name: str, ok: bool, msg: str) -> None:
    if not ok:
        raise InvalidInputError(f"{name}: {msg}", name)


class HybridSimulator:
    """Neural physics with an MPM fallback (paper Sec. 3.1.2).

    Parameters
    ----------
    scene:
        A :class:`~hybridmpm.scenes.Scene` at full resolution (or a registered
        scene name / scene file, built with ``seed``).
    model:
        :class:`~hybridmpm.neural.NeuralModel`, ``.onnx`` path, or None for the
        shipped model of the scene.
    r_c, delta, dwell:
        Safeguard threshold (default 0.8), window δ in steps (10), and steps
        of ``s ≥ r_c`` on MPM before returning to the network (default
        :data:`DWELL`).
    seed:
        Seed of the scene (if a name) and of the r_p clustering.
    affine, volume_ratio:
        APIC ``C`` after neural → MPM: "fit" (neighbour least squares) or
        "zero"; water's ``J``: "density" (from the local density) or "one".
    accel_floor:
        [m/s²] particles calmer than this count as cos = 1 in s(t).
    ke_factor, escape_cells, degree_factor:
        Blow-up bounds of a neural step (see the module docstring).
    detect_failures:
        False turns the blow-up checks off: with ``r_c ≤ 0`` the simulator is
        then the network alone (:func:`~hybridmpm.neural.runtime.run_neural`,
        bit for bit), for benchmarks.
    mpm_threads, nn_threads:
        Threads of the MPM solver (0 = all cores) and of onnxruntime.

    Raises :class:`InvalidInputError` naming the parameter for out-of-range
    values or a model that does not fit the scene.
    """

    def __init__(
        self,
        scene: Scene | str,
        model: NeuralModel | str | Path | None = None,
        *,
        r_c: float = R_C,
        delta: int = DELTA,
        dwell: int = DWELL,
        seed: int = 0,
        affine: str = "fit",
        volume_ratio: str = "density",
        accel_floor: float = ACCEL_FLOOR,
        ke_factor: float = 2.0,
        escape_cells: float = 4.0,
        degree_factor: float = 2.0,
        detect_failures: bool = True,
        mpm_threads: int = 0,
        nn_threads: int = 1,
    ) -> None:
        from hybridmpm.data.resolution import downsample_scene
        from hybridmpm.models import shipped_model
        from hybridmpm.scenes import make_scene

        _check("r_c", isinstance(r_c, (int, float)) and math.isfinite(r_c), f"must be a finite number, got {r_c!r}")
        _check("delta", isinstance(delta, int) and delta >= 1, f"must be an integer >= 1, got {delta!r}")
        _check("dwell", isinstance(dwell, int) and dwell >= 1, f"must be an integer >= 1, got {dwell!r}")
        _check("affine", affine in ("fit", "zero"), f"must be 'fit' or 'zero', got {affine!r}")
        _check("volume_ratio", volume_ratio in ("density", "one"), f"must be 'density' or 'one', got {volume_ratio!r}")
        _check("accel_floor", math.isfinite(accel_floor) and accel_floor >= 0, f"must be >= 0 [m/s²], got {accel_floor!r}")
        _check("ke_factor", math.isfinite(ke_factor) and ke_factor > 0, f"must be > 0, got {ke_factor!r}")
        _check("escape_cells", math.isfinite(escape_cells) and escape_cells >= 0, f"must be >= 0, got {escape_cells!r}")
        _check("degree_factor", math.isfinite(degree_factor) and degree_factor > 1, f"must be > 1, got {degree_factor!r}")
        if isinstance(scene, str):
            scene = make_scene(scene, seed=seed)
        self.scene_full = scene
        if model is None:
            model = shipped_model(scene.name)
        self.model = model if isinstance(model, NeuralModel) else NeuralModel(model, threads=nn_threads)
        self.r_c = float(r_c)
        self.delta = delta
        self.dwell = dwell
        self.affine = affine
        self.volume_ratio = volume_ratio
        self.accel_floor = float(accel_floor)
        self.ke_factor = float(ke_factor)
        self.escape_cells = float(escape_cells)
        self.degree_factor = float(degree_factor)
        self.detect_failures = bool(detect_failures)

        self.scene = downsample_scene(scene, self.model.r_p, seed=seed).scene if self.model.r_p < 1.0 else scene
        self.particle_type = self.scene.particle_type()
        self.model.check_fits(self.scene.dim, self.particle_type, getattr(scene, "name", None))
        self.solver: MpmSolver = self.scene.make_solver(num_threads=mpm_threads)
        self.r_t = self.model.r_t
        self.t_in = self.model.t_in
        self.dt_frame = float(self.scene.dt_frame)
        self.dt_step = self.dt_frame * self.r_t
        self.n_fluid = self.scene.num_particles
        self.masses = np.asarray(self.solver.masses, np.float64)
        lo, hi = self.solver.domain_bounds
        self._lo, self._hi = lo, hi
        mb = np.asarray(self.model.meta["bounds"], np.float32)
        self._model_lo, self._model_hi = mb[:, 0], mb[:, 1]
        g = np.asarray(self.scene.params.to_dict()["gravity"], np.float64)
        self._g = g
        x0 = np.asarray(self.scene.positions, np.float64)
        v0 = np.asarray(self.scene.velocities, np.float64)
        self.energy_budget = float(
            0.5 * (self.masses * (v0**2).sum(1)).sum() + (self.masses * ((x0 - lo) @ -g).clip(min=0)).sum()
        )
        self._buffer: deque[np.ndarray] = deque(maxlen=max(2 * delta + 2, self.t_in))
        self._buffer.append(np.asarray(self.solver.positions, np.float32).copy())
        self.solver_name = MPM
        self._calm = 0
        self._strikes = 0
        self._neural_run = 0
        self._neural: NeuralSimulator | None = None
        self.step_index = 0
        self.stats = HybridStats()
        self.last_score = float("nan")
        # mean neighbours per particle of the initial condition (the fluid's rest spacing)
        x0b = self.scene.with_boundary(np.asarray(self.scene.positions, np.float32))
        self._degree0 = len(radius_graph(x0b, self.model.radius)[0]) / max(1, len(x0b))
        self._next_graph: tuple[np.ndarray, np.ndarray] | None = None

    # ------------------------------------------------------------ properties
    @property
    def positions(self) -> np.ndarray:
        """Current positions with boundary particles, float32 [N + B, D]."""
        return self.scene.with_boundary(self._buffer[-1])

    @property
    def mean_degree(self) -> float:
        """Mean neighbours per particle (self-edge included) of the network's
        graph for its next step; nan when the next step is MPM's."""
        if self._next_graph is None:
            return float("nan")
        return len(self._next_graph[0]) / max(1, len(self.particle_type))

    @property
    def initial_degree(self) -> float:
        """Mean neighbours per particle of the initial condition (the fluid at rest spacing)."""
        return float(self._degree0)

    @property
    def safeguard_on(self) -> bool:
        return self.r_c > 0.0

    def initial_frame(self) -> Frame:
        """The initial condition (at the model's r_p) as a :class:`Frame`."""
        return Frame(0, 0, 0.0, self.scene.with_boundary(np.asarray(self.scene.positions, np.float32)), MPM, 0.0, float("nan"))

    # ------------------------------------------------------------ stepping
    def _mpm_step(self) -> tuple[np.ndarray, int]:
        retries = 0
        for _ in range(self.r_t):
            st = self.solver.step_frame(self.dt_frame)
            retries += int(st.get("retries", 0))
        return np.asarray(self.solver.positions, np.float32).copy(), retries

    def _neural_failure(self, nxt: np.ndarray) -> str | None:
        fluid = nxt[: self.n_fluid]
        if not np.isfinite(fluid).all():
            return "nan"
        margin = self.escape_cells * self.solver.dx
        if (fluid < self._model_lo - margin).any() or (fluid > self._model_hi + margin).any():
            return "escaped"
        v = (fluid.astype(np.float64) - self._buffer[-1]) / self.dt_step
        ke = 0.5 * float((self.masses * (v**2).sum(1)).sum())
        if ke > self.ke_factor * self.energy_budget:
            return "energy"
        return None

    def _to_mpm(self) -> None:
        self._next_graph = None
        hist = np.stack(list(self._buffer)[-2:])
        neural_to_mpm(self.solver, hist, self.dt_step, affine=self.affine, affine_radius=self.model.radius, volume_ratio=self.volume_ratio)
        self._neural = None

    def _to_neural(self) -> None:
        # called after an MPM step: the buffer's newest entry is the solver's state
        hist = mpm_history(self.solver, np.stack(list(self._buffer)[-self.t_in : -1]), self.t_in)
        self._neural = NeuralSimulator(self.model, self.scene.with_boundary(hist), self.particle_type)
        self._next_graph = None

    def advance(self) -> Frame:
        """One coarse step (``r_t`` frames); returns its :class:`Frame`.

        Raises :class:`~hybridmpm.errors.SimulationError` if MPM fails even
        with ``max_substeps`` (the simulator state is then that before the step).
        """
        t0 = time.perf_counter()
        event: str | None = None
        retries = 0
        ran = self.solver_name
        if ran == NEURAL:
            assert self._neural is not None
            _, nxt, _ = self.model.predict(self._neural.history, self._neural.particle_type, None, graph=self._next_graph)
            self._next_graph = None
            failure = self._neural_failure(nxt) if self.detect_failures else None
            if failure is None:
                # the graph of the clipped prediction: checked for compression, then reused by the next predict
                clipped = self._neural.clip(nxt)
                s_next, r_next, _, _ = radius_graph(clipped, self.model.radius)
                if self.detect_failures and len(s_next) > self.degree_factor * self._degree0 * len(clipped):
                    failure = "compressed"
                else:
                    self._next_graph = (s_next, r_next)
            if failure is None:
                pos = self._neural.push(clipped)[: self.n_fluid].copy()
                self._neural_run += 1
                if self._neural_run >= 2 * self.dwell:
                    self._strikes = 0  # a healthy stint: forgive earlier failures
            else:
                event = f"fallback:{failure}"
                self._strikes += 1
                self.stats.fallbacks[failure] = self.stats.fallbacks.get(failure, 0) + 1
                self._to_mpm()
                self.solver_name = MPM
                self._calm = 0
                self.stats.switches += 1
                ran = MPM
        if ran == MPM:
            pos, retries = self._mpm_step()
        self._buffer.append(pos)
        self.step_index += 1
        self.stats.steps[ran] += 1
        self.stats.mpm_retries += retries

        # safeguard on the trajectory, whichever solver made it
        score = complexity_score(np.stack(self._buffer), self.dt_step, self.delta, self.accel_floor) if self.safeguard_on else float("nan")
        self.last_score = score
        warm = self.step_index >= self.t_in - 1
        if self.solver_name == NEURAL:
            if self.safeguard_on and not (score >= self.r_c):
                self._to_mpm()
                self.solver_name = MPM
                self._calm = 0
                self.stats.switches += 1
                event = event or "switch:mpm"
        elif warm:
            ok = (not self.safeguard_on) or score >= self.r_c
            self._calm = self._calm + 1 if ok else 0
            # after the warm-up a calm score hands over at once; after a switch it must hold for `dwell`
            # steps, doubled for each failure of the network since its last healthy stint (backoff)
            if self.stats.steps[NEURAL] == 0 and self.stats.switches == 0:
                need = 1
            else:
                need = self.dwell * 2 ** min(self._strikes, MAX_BACKOFF)
            if self._calm >= need and len(self._buffer) >= self.t_in:
                self._to_neural()
                self.solver_name = NEURAL
                self._neural_run = 0
                if self.stats.steps[NEURAL] > 0 or self.stats.switches > 0:
                    self.stats.switches += 1
                    event = event or "switch:neural"
        seconds = time.perf_counter() - t0
        return Frame(
            self.step_index,
            self.step_index * self.r_t,
            self.step_index * self.dt_step,
            self.scene.with_boundary(pos),
            ran,
            seconds,
            score,
            event,
            retries,
        )

    def step(self, frames: int | None = None) -> Iterator[Frame]:
        """Generator of :class:`Frame` s, one per coarse step, until ``frames``
        frames have been simulated (None: forever). The initial condition is
        not yielded (see :meth:`initial_frame`)."""
        _check("frames", frames is None or (isinstance(frames, int) and frames >= 0), f"must be an integer >= 0, got {frames!r}")
        while frames is None or self.step_index * self.r_t < frames:
            yield self.advance()

    # ------------------------------------------------------------ checkpoint
    def state(self) -> dict[str, Any]:
        """The whole hybrid state (picklable dict): MPM solver checkpoint,
        position buffer, solver in charge, counters."""
        return {
            "version": 1,
            "solver_checkpoint": self.solver.checkpoint(),
            "buffer": np.stack(list(self._buffer)).copy(),
            "solver_name": self.solver_name,
            "calm": self._calm,
            "strikes": self._strikes,
            "neural_run": self._neural_run,
            "step_index": self.step_index,
            "neural_history": None if self._neural is None else self._neural.history.copy(),
            "stats": {
                "steps": dict(self.stats.steps),
                "switches": self.stats.switches,
                "fallbacks": dict(self.stats.fallbacks),
                "mpm_retries": self.stats.mpm_retries,
            },
            "last_score": self.last_score,
            "n_fluid": self.n_fluid,
        }

    def restore(self, state: dict[str, Any]) -> None:
        """Restore a :meth:`state` of this simulator (same scene and model).
        Raises :class:`InvalidInputError` (field ``state``) for a foreign state."""
        try:
            if state.get("version") != 1 or int(state["n_fluid"]) != self.n_fluid:
                raise InvalidInputError("state: not a state of this hybrid simulator (version or particle count differ)", "state")
            buf = np.asarray(state["buffer"], np.float32)
            if buf.ndim != 3 or buf.shape[1] != self.n_fluid:
                raise InvalidInputError(f"state: buffer has shape {list(buf.shape)}, expected [T, {self.n_fluid}, D]", "state")
            self.solver.restore(state["solver_checkpoint"])
            self._buffer = deque([b for b in buf], maxlen=self._buffer.maxlen)
            self.solver_name = str(state["solver_name"])
            self._calm = int(state["calm"])
            self._strikes = int(state["strikes"])
            self._neural_run = int(state["neural_run"])
            self.step_index = int(state["step_index"])
            nh = state["neural_history"]
            self._neural = None
            self._next_graph = None
            if nh is not None:
                self._neural = NeuralSimulator(self.model, np.asarray(nh, np.float32), self.particle_type)
            st = state["stats"]
            self.stats = HybridStats(dict(st["steps"]), int(st["switches"]), dict(st["fallbacks"]), int(st["mpm_retries"]))
            self.last_score = float(state["last_score"])
        except (KeyError, TypeError, ValueError) as e:
            raise InvalidInputError(f"state: malformed hybrid state ({e})", "state") from e


__all__ = ["DWELL", "MAX_BACKOFF", "MPM", "NEURAL", "Frame", "HybridSimulator", "HybridStats"]
