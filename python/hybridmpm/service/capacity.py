"""Real-time capacity: how many real-time sessions a server holds (docs/service.md, "Real-time sessions").

A real-time session that plays steps ``dt_frame`` of simulated time per ``dt_frame`` of wall time, so it keeps
``frame / dt_frame`` of each of its MPM threads busy: its **cores**, measured by its own frame timing
(:meth:`~hybridmpm.sim.RealtimeSimulator.realtime_info`). The server's real-time capacity is
:data:`REALTIME_SHARE` of its compute threads. A new real-time session is admitted when its estimated cores fit
what the playing ones leave:

* at its most accurate rung when that fits, or when no other real-time session plays (a session alone is
  never refused: its own mode finds the rung the machine holds);
* else, when the request says ``"when_full": "coarser"``, at the most accurate rung that fits;
* else refused (503), the message saying how many run and at what cost.

A rung's estimate is its chart time (``models/realtime.json``) scaled by this machine's pace: the median, over
the playing real-time sessions, of their measured time a frame over their rung's chart time (1 while none
plays). Sessions that do not play (or that nobody watches: their play loop waits) take no cores here: a session that
starts playing later is not refused. While they play, each real-time session's frame budget is its share of the
capacity (:func:`realtime_share`), so all of them step down as the machine fills. On the Ray backend each actor
takes the same rule (:func:`share_of`) over the real-time sessions playing on its node
(:mod:`hybridmpm.service.ray_backend.shares`).
"""

from __future__ import annotations

import statistics
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from hybridmpm.sim import RealtimeSimulator

#: The share of the compute threads real-time sessions may fill (the rest: serving, the event loop, the page).
REALTIME_SHARE = 0.9
#: What a real-time session asks when the server is full: a 503, or a coarser rung that fits.
WHEN_FULL = ("refuse", "coarser")


class RealtimeFullError(Exception):
    """No room at real time for another real-time session (→ 503 with this message)."""


@dataclass(frozen=True)
class Playing:
    """One playing real-time session as capacity sees it: ``cores`` it keeps busy at real time, and
    ``pace`` its measured time a frame over its rung's chart time (None without a chart entry)."""

    cores: float
    pace: float | None


def chart_ms(sim: RealtimeSimulator, key: str) -> float | None:
    """The chart's time a frame of ``sim``'s scene on rung ``key`` [ms] (this chart's machine), or None."""
    chart = getattr(sim, "chart", None)
    if not chart:
        return None
    return next((float(r["ms"]) for r in chart.get("rungs", []) if r.get("key") == key and r.get("ms")), None)


def playing(sim: Any, threads: int) -> Playing | None:
    """``sim``'s load when it is a real-time simulator that has timed its frames, else None."""
    if not isinstance(sim, RealtimeSimulator):
        return None
    info = sim.realtime_info()
    if info["frame_ms"] is None:
        return None
    cores = min(float(threads), info["frame_ms"] / (sim.dt_step * 1e3) * threads)
    ref = chart_ms(sim, info["rung"])
    return Playing(cores, None if not ref else info["frame_ms"] / ref)


def admit(sim: RealtimeSimulator, threads: int, others: Iterable[Playing], compute_threads: int, when_full: str) -> str:
    """The rung a new real-time session ``sim`` (built, not yet stepped; ``threads`` MPM threads) starts on, given
    the ``others`` playing; raises :class:`RealtimeFullError` when none fits (``when_full`` "refuse": its most
    accurate rung must fit; "coarser": any rung)."""
    others = list(others)
    if not others:  # alone it is always admitted, at its best: its own mode then finds the rung this machine holds
        return sim.ladder[0].key
    used = sum(p.cores for p in others)
    capacity = REALTIME_SHARE * compute_threads
    paces = [p.pace for p in others if p.pace is not None]
    pace = statistics.median(paces) if paces else 1.0
    needs = []
    for r in sim.ladder:
        ms = chart_ms(sim, r.key)
        needs.append((r.key, None if ms is None else min(float(threads), ms * pace / (sim.dt_step * 1e3) * threads)))
    allowed = needs[:1] if when_full == "refuse" else needs
    for key, need in allowed:
        if need is None or used + need <= capacity:
            return key
    best, least = needs[0][1] or 0.0, needs[-1][1] or 0.0
    raise RealtimeFullError(
        f"real time is full here: {len(others)} real-time sessions play, using {used:.2f} of the {capacity:.2f} cores real time may take "
        f"({REALTIME_SHARE:.0%} of {compute_threads}); this one needs about {best:.2f} at its most accurate configuration "
        f"and {least:.2f} at its coarsest" + ("; ask with when_full 'coarser' to start coarser, or retry later" if when_full == "refuse" else "; retry later")
    )


def share_of(threads: float, compute_threads: float) -> float:
    """The share of its threads' time each playing real-time session may spend (in (0, 1]) where the playing
    real-time sessions step on ``threads`` MPM threads in all (0 or less: none plays) on a machine (or Ray node) of
    ``compute_threads`` threads (its cores, or the CPUs the node offers): :data:`REALTIME_SHARE` of
    ``compute_threads`` over ``threads``, at most 1. The one rule of both backends (:func:`realtime_share`,
    :mod:`hybridmpm.service.ray_backend.shares`). Raises ValueError when ``compute_threads`` is not positive."""
    if not compute_threads > 0:
        raise ValueError(f"compute_threads: must be positive, got {compute_threads!r}")
    return 1.0 if threads <= 0 else min(1.0, REALTIME_SHARE * compute_threads / threads)


def realtime_share(held: Iterable[Any], compute_threads: int) -> float:
    """The share of its threads' time each playing real-time session of ``held`` (session cores) may spend
    (:func:`share_of` the threads of those that play with viewers, ``compute_threads``). A session's frames run
    one at a time on its threads (the compute limiter), so its own frame times do not see the others; with the
    share in its budget (:meth:`~hybridmpm.sim.RealtimeSimulator.set_share`) each steps down to a rung that fits
    its part of the machine. Raises ValueError when ``compute_threads`` is not positive."""
    return share_of(sum(c.threads for c in held if isinstance(c.sim, RealtimeSimulator) and c.playing and c.has_viewers()), compute_threads)


def admit_session(core: Any, held: Iterable[Any], compute_threads: int, when_full: str) -> None:
    """Admit a new session ``core`` (a :class:`~hybridmpm.service.core.SessionCore`, built, not yet stepped) beside
    the sessions ``held`` (theirs): a real-time one moves to the rung :func:`admit` gives for the playing ones (and a
    reset starts there), or :class:`RealtimeFullError` is raised; any other session is admitted as it is."""
    sim = core.sim
    if not isinstance(sim, RealtimeSimulator):
        return
    others = [playing(c.sim, c.threads) for c in held if c.playing and c.has_viewers()]  # a play loop runs only while watched
    sim.set_rung(admit(sim, core.threads, [p for p in others if p is not None], compute_threads, when_full))
    core.initial = sim.state()


__all__ = ["REALTIME_SHARE", "WHEN_FULL", "Playing", "RealtimeFullError", "admit", "admit_session", "chart_ms", "playing", "realtime_share", "share_of"]
