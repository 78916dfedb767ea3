"""The simulator interface every solver shares (docs/design.md "Data flow").

A simulator advances one *coarse step* at a time — ``r_t`` frames of
``dt_frame`` seconds (MPM: ``r_t = 1`` unless asked otherwise; the network:
its model's ``r_t``) — and returns a :class:`Frame`. :func:`~hybridmpm.sim.rollout`
drives any of them; the CLI, the benchmarks, dataset generation, the
controller and the service all go through it.

``forcing`` is the controller's hook (paper Sec. 3.2): a per-particle external
acceleration [m/s²] that MPM adds to gravity, given as an array ``[N, D]``
(fluid particles), as a callable ``forcing(frame, positions, velocities)`` of
the frame index and the fluid state it acts on (float32 [N, D] m and m/s, read
by the simulator that applies it at the start of that frame) returning such an
array (or None for "no forcing in this frame"), or None. The network cannot
apply a forcing: the hybrid runs MPM while one is set, and its MPM hands the
callable the state.

Threads: a simulator may be shared between threads. Its mutating calls
(``advance``, ``state``, ``restore``, setting ``forcing``) are serialised by
a per-simulator lock: a second caller waits for the call in progress. Reading
``frame`` never waits: it is the last completed :class:`Frame`, a snapshot
whose arrays no later step changes.
"""

from __future__ import annotations

import contextlib
import functools
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeVar, Union, cast, runtime_checkable

import numpy as np

from hybridmpm.errors import InvalidInputError, SimulationError
from hybridmpm.limits import MAX_FRAME_INDEX
from hybridmpm.scenes.core import Scene
from hybridmpm.scenes.particles import ParticleSet

#: Solver tags of a :class:`Frame`.
MPM = "mpm"
NEURAL = "neural"

#: A forcing function: ``(frame, positions, velocities) -> accelerations | None``, the fluid's state float32 [N, D]
#: (m, m/s) at the start of frame ``frame`` in, its accelerations [N, D] m/s² out (None: no forcing in this frame).
ForcingFunction = Callable[[int, np.ndarray, np.ndarray], Union[np.ndarray, None]]
#: A forcing: fluid accelerations [N, D] m/s², a :data:`ForcingFunction`, or None.
Forcing = Union[np.ndarray, ForcingFunction, None]


@dataclass
class Frame:
    """One coarse step of a simulator.

    ``step`` coarse step index (0 = initial condition); ``frame_index`` frame
    number (``step·r_t``); ``time`` [s]; ``positions`` float32 [N + B, D] [m] (fluid,
    then boundary particles, each obstacle's at its current pose; see
    :class:`~hybridmpm.scenes.ParticleSet`);
    ``solver`` "mpm" or "neural" (the one that produced these positions);
    ``seconds`` wall time of the step; ``score`` the safeguard ``s(t)`` after
    the step (nan where not computed); ``event`` None or what happened
    ("switch:mpm", "switch:neural", "fallback:<mode>"); ``mpm_retries`` substep
    halvings MPM needed; ``substeps`` MPM substeps taken (0 for a network step);
    ``controlled`` whether a forcing was applied during the step; ``audit``
    the MPM audit's discrepancy of a network step in units of g (see
    :class:`~hybridmpm.sim.hybrid.HybridSimulator`; nan where none ran);
    ``obstacle_centers`` float64 [C, D] [m] each obstacle's centre at the
    frame's end (:attr:`~hybridmpm.sim.MpmSimulator.obstacle_centers`;
    None in a scene without obstacles, and from the network alone, whose
    obstacles stand where the scene put them).
    ``body_center`` float64 [B, D] [m], ``body_rotation`` [B, D, D] and
    ``body_mass`` [B] [kg; per unit depth in 2D]: the rigid bodies at the
    frame's end (None in a scene without bodies).
    """

    step: int
    frame_index: int
    time: float
    positions: np.ndarray
    solver: str
    seconds: float = 0.0
    score: float = float("nan")
    event: str | None = None
    mpm_retries: int = 0
    substeps: int = 0
    controlled: bool = False
    audit: float = float("nan")
    obstacle_centers: np.ndarray | None = None
    body_center: np.ndarray | None = None
    body_rotation: np.ndarray | None = None
    body_mass: np.ndarray | None = None


@dataclass
class SimStats:
    """Counters of a run: coarse ``steps`` per solver, solver ``switches``,
    network ``fallbacks`` per failure mode, MPM substep halvings
    ``mpm_retries``, projection steps replanned shorter before their
    particles moved ``mpm_replans`` (docs/large-step.md), MPM ``audits`` of
    network steps run and the wall ``audit_seconds`` they took."""

    steps: dict[str, int] = field(default_factory=lambda: {MPM: 0, NEURAL: 0})
    switches: int = 0
    fallbacks: dict[str, int] = field(default_factory=dict)
    mpm_retries: int = 0
    audits: int = 0
    audit_seconds: float = 0.0
    mpm_replans: int = 0

    def to_dict(self) -> dict[str, Any]:
        return {
            "steps": dict(self.steps),
            "switches": self.switches,
            "fallbacks": dict(self.fallbacks),
            "mpm_retries": self.mpm_retries,
            "audits": self.audits,
            "audit_seconds": self.audit_seconds,
            "mpm_replans": self.mpm_replans,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SimStats:
        """The counters of :meth:`to_dict`; each an integer in [0,
        :data:`~hybridmpm.limits.MAX_FRAME_INDEX`] (else
        :class:`InvalidInputError` naming ``state.stats.<key>``)."""

        def counts(key: str) -> dict[str, int]:
            v = d[key]
            if not isinstance(v, dict) or not all(isinstance(k, str) for k in v):
                raise InvalidInputError(f"state.stats.{key}: must be an object of counters", f"state.stats.{key}")
            return {k: check_count(f"state.stats.{key}.{k}", x) for k, x in v.items()}

        secs = d.get("audit_seconds", 0.0)
        if isinstance(secs, bool) or not isinstance(secs, (int, float)) or not 0 <= float(secs) < float("inf"):
            raise InvalidInputError("state.stats.audit_seconds: must be a finite number >= 0", "state.stats.audit_seconds")
        return cls(
            counts("steps"),
            check_count("state.stats.switches", d["switches"]),
            counts("fallbacks"),
            check_count("state.stats.mpm_retries", d["mpm_retries"]),
            check_count("state.stats.audits", d.get("audits", 0)),  # states saved before the audit existed have none
            float(secs),
            check_count("state.stats.mpm_replans", d.get("mpm_replans", 0)),  # nor before replanning
        )


class NetworkFailure(SimulationError):
    """A network step was rejected by the failure checks (``mode``: "nan",
    "escaped", "energy" or "compressed"); the simulator's state is that
    before the step."""

    def __init__(self, mode: str, step: int) -> None:
        super().__init__(f"network step {step} rejected: {mode}")
        self.mode = mode


@runtime_checkable
class Simulator(Protocol):
    """What :class:`MpmSimulator`, :class:`NeuralSimulator` and
    :class:`HybridSimulator` share.

    ``scene`` the scene as simulated (at the simulator's ``r_p``);
    ``particles`` its :class:`ParticleSet`; ``r_t`` frames per coarse step;
    ``dt_frame`` [s]; ``step_index`` coarse steps taken; ``frame`` the
    current :class:`Frame` (the initial condition before the first step);
    ``stats`` the run's :class:`SimStats`; ``forcing`` see the module doc;
    ``positions`` float32 [N + B, D] and ``velocities`` (fluid) float32 [N, D]
    of the current state.
    """

    kind: str
    scene: Scene
    particles: ParticleSet
    r_t: int
    dt_frame: float
    step_index: int
    stats: SimStats

    @property
    def positions(self) -> np.ndarray: ...

    @property
    def velocities(self) -> np.ndarray: ...

    @property
    def frame(self) -> Frame: ...

    @property
    def forcing(self) -> Forcing: ...

    @forcing.setter
    def forcing(self, value: Forcing) -> None: ...

    def advance(self) -> Frame: ...

    def state(self) -> dict[str, Any]: ...

    def restore(self, state: dict[str, Any]) -> None: ...


_F = TypeVar("_F", bound=Callable[..., Any])


def serialised(method: _F) -> _F:
    """Run ``method`` under the instance's re-entrant ``_lock`` (see the module doc)."""

    @functools.wraps(method)
    def wrapper(self: Any, *args: Any, **kwargs: Any) -> Any:
        with self._lock:
            return method(self, *args, **kwargs)

    return cast(_F, wrapper)


@contextlib.contextmanager
def reading_state(kind: str) -> Iterator[None]:
    """Turn what reading a malformed ``state()`` dict raises (a missing key, a
    value of the wrong type) into :class:`InvalidInputError` (field ``state``;
    the message names the key, ``state.buffer: ...``)."""
    try:
        yield
    except InvalidInputError as e:
        if e.field is not None and e.field.startswith("state"):
            e.field = "state"
        raise
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        raise InvalidInputError(f"state: malformed {kind} state ({e})", "state") from e


def new_lock() -> threading.RLock:
    """The lock :func:`serialised` methods take (one per simulator)."""
    return threading.RLock()


def check_forcing(value: Forcing, n: int, dim: int) -> Forcing:
    """Validate a forcing for ``n`` fluid particles in ``dim`` dimensions: an
    array becomes float32 [n, dim] (finite); a callable is kept (its results
    are checked by :func:`resolve_forcing` when used). Raises
    :class:`InvalidInputError` (field ``forcing``)."""
    if value is None or callable(value):
        return value
    a = np.asarray(value)
    if a.dtype.kind not in "fiu" or a.shape != (n, dim):
        raise InvalidInputError(f"forcing: expected a float array [{n}, {dim}] of accelerations [m/s²], got {a.dtype} {list(a.shape)}", "forcing")
    a = np.ascontiguousarray(a, np.float32)
    if not np.isfinite(a).all():
        raise InvalidInputError("forcing: contains NaN or inf", "forcing")
    return a


def resolve_forcing(value: Forcing, frame: int, n: int, dim: int, state: Callable[[], tuple[np.ndarray, np.ndarray]]) -> np.ndarray | None:
    """The forcing to apply to frame ``frame``: float32 [n, dim] or None. A
    callable forcing is handed the fluid's ``state()`` (positions, velocities),
    read only then."""
    if value is None:
        return None
    if callable(value):
        out = value(int(frame), *state())
        if out is None:
            return None
        checked = check_forcing(np.asarray(out), n, dim)
        assert isinstance(checked, np.ndarray)
        return checked
    return value


def check_int(name: str, value: Any, lo: int, hi: int | None = None) -> int:
    """``value`` as an int in [``lo``, ``hi``], or :class:`InvalidInputError` naming ``name``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or int(value) < lo or (hi is not None and int(value) > hi):
        shown = repr(value) if len(repr(value)) <= 40 else f"{type(value).__name__} {repr(value)[:30]}…"
        bound = f"an integer >= {lo}" if hi is None else f"an integer in [{lo}, {hi}]"
        raise InvalidInputError(f"{name}: must be {bound}, got {shown}", name)
    return int(value)


def check_count(name: str, value: Any) -> int:
    """A counter of steps or frames of a restored state: an integer in [0,
    :data:`~hybridmpm.limits.MAX_FRAME_INDEX`], or :class:`InvalidInputError` naming ``name``."""
    return check_int(name, value, 0, MAX_FRAME_INDEX)


def check_step_index(name: str, value: Any, r_t: int) -> int:
    """A restored ``step_index``: a counter whose frame ``value · r_t`` is at
    most :data:`~hybridmpm.limits.MAX_FRAME_INDEX`."""
    return check_int(name, value, 0, MAX_FRAME_INDEX // max(1, int(r_t)))


def check_positions(name: str, value: Any, shape: tuple[int, ...]) -> np.ndarray:
    """A restored positions array: float32 of exactly ``shape``, finite.
    Raises :class:`InvalidInputError` naming ``name``."""
    a = np.asarray(value)
    if a.dtype.kind not in "fiu" or a.shape != shape:
        raise InvalidInputError(f"{name}: must be a float array {list(shape)}, got {a.dtype} {list(a.shape)}", name)
    a = np.array(a, np.float32)
    if not np.isfinite(a).all():
        raise InvalidInputError(f"{name}: contains NaN or inf", name)
    return a


__all__ = [
    "MPM",
    "NEURAL",
    "Forcing",
    "ForcingFunction",
    "Frame",
    "NetworkFailure",
    "SimStats",
    "Simulator",
    "check_count",
    "check_forcing",
    "check_int",
    "check_positions",
    "check_step_index",
    "new_lock",
    "reading_state",
    "resolve_forcing",
    "serialised",
]
