"""What both backends do the same way with a session, written once: the
paced play step (real time, catching up at most :data:`PLAY_LAG_S`), the
step a playing session takes, and the record a save writes. The local
manager runs them on its event loop and workers
(:class:`~hybridmpm.service.sessions.SessionManager`), the Ray actor in its
own threads (:class:`~hybridmpm.service.actor.SessionActor`).
"""

from __future__ import annotations

import time
from typing import Any

from hybridmpm.service import checkpoint as ckpt
from hybridmpm.service.store import record_state
from hybridmpm.sim import Frame, Simulator

#: How far a playing session may fall behind real time before it stops catching up [s].
PLAY_LAG_S = 0.25


class Pacer:
    """Real-time pacing of a playing session: one coarse step (``period``
    seconds of simulated time) per ``period`` seconds of wall time;
    :meth:`delay` after each step says how long to wait before the next.
    A session that falls behind catches up at most :data:`PLAY_LAG_S`."""

    def __init__(self, period: float) -> None:
        self.period = float(period)
        self.next_t = time.monotonic()

    def delay(self) -> float:
        """Seconds to wait before the next step [s], ≥ 0."""
        self.next_t = max(self.next_t + self.period, time.monotonic() - PLAY_LAG_S)
        return max(0.0, self.next_t - time.monotonic())


def play_period(sim: Simulator) -> float:
    """Wall seconds per step of a playing session: its coarse step, ``dt_frame · r_t`` [s]."""
    return float(sim.dt_frame) * int(sim.r_t)


def play_step(sim: Simulator) -> Frame:
    """One step of a playing session (the caller holds its lock): ``sim.advance()``."""
    return sim.advance()


def snapshot(sim: Simulator) -> tuple[dict[str, Any], int]:
    """The state a save writes (:func:`~hybridmpm.service.store.record_state`) and its frame; under the session's lock."""
    return record_state(sim), int(sim.frame.frame_index)


def encode_record(state: dict[str, Any], settings: dict[str, Any], last_used: float, client: str) -> bytes:
    """The bytes of a session's record in the store: its ``state``, what rebuilds
    it (``settings``: scene, seed, solver, ``r_c``, ``n_grid``), when it was last
    used (``last_used``, a ``time.monotonic()``, written as wall time) and the
    client address that created it (the per-client quota)."""
    meta = {
        **settings,
        "last_used_at": time.time() - (time.monotonic() - last_used),
        "client": client[: ckpt.MAX_META_CHARS],
    }
    return ckpt.dumps(state, meta)


__all__ = ["PLAY_LAG_S", "Pacer", "encode_record", "play_period", "play_step", "snapshot"]
