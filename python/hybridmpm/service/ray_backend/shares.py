"""Real-time shares on a Ray cluster: each playing real-time session's actor gets its part of its *node*'s
CPUs as a smaller frame budget, by the local backend's rule (:func:`hybridmpm.service.capacity.share_of`).

While its play loop runs, a real-time session's actor reports "I play real time on node N with T threads" to
the namespace's registry every :data:`SHARE_REFRESH_S` (:class:`ShareReporter`, without waiting for the answer
in the play loop), and "I stopped" when the loop ends; the registry (:class:`NodeLoads`) answers the threads of
the node's fresh reports and the CPUs the node offers, from which the actor sets its simulator's share
(:meth:`~hybridmpm.sim.RealtimeSimulator.set_share`). A report not renewed within :data:`SHARE_EXPIRE_S` (an actor
whose process died) no longer counts; a session that is deleted leaves at once (the registry's ``release``).
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections.abc import Callable
from typing import Any

import ray

from hybridmpm.service.capacity import share_of
from hybridmpm.service.store import SHOWN_KEY_CHARS

log = logging.getLogger("hybridmpm.service")

#: How often a playing real-time session's actor reports to the registry and takes up its share [s].
SHARE_REFRESH_S = 0.5
#: A report counts this long without being renewed [s] (then its actor is taken for gone).
SHARE_EXPIRE_S = 3.0


class NodeLoads:
    """The threads the playing real-time sessions step on, per node (the registry's; plain Python, no Ray):
    :meth:`report` records a session's threads and answers its node's total. ``clock`` (seconds, monotonic) and
    ``expire_s`` (seconds a report counts unrenewed) are for tests."""

    def __init__(self, clock: Callable[[], float] = time.monotonic, expire_s: float = SHARE_EXPIRE_S) -> None:
        self.clock, self.expire_s = clock, float(expire_s)
        self.nodes: dict[str, dict[str, tuple[int, float]]] = {}  # node id -> session key -> (threads, reported at)

    def report(self, node: str, key: str, threads: int) -> int:
        """Session ``key`` plays real time on ``node`` with ``threads`` MPM threads (0: it stopped); the threads
        of the node's reports renewed within ``expire_s`` (older ones are dropped), this one included."""
        now = self.clock()
        on = self.nodes.setdefault(node, {})
        if threads > 0:
            on[key] = (int(threads), now)
        else:
            on.pop(key, None)
        for k, (_, at) in list(on.items()):
            if now - at > self.expire_s:
                del on[k]
        if not on:
            del self.nodes[node]
        return sum(t for t, _ in on.values())

    def drop(self, key: str) -> None:
        """Session ``key`` is gone: its report (on any node) no longer counts."""
        for node, on in list(self.nodes.items()):
            on.pop(key, None)
            if not on:
                del self.nodes[node]


def node_cpus() -> dict[str, float]:
    """The CPUs each live node of the cluster offers (its ``CPU`` resource), by node id (hex). Blocks (the GCS)."""
    return {str(n["NodeID"]): float(n.get("Resources", {}).get("CPU", 0.0)) for n in ray.nodes() if n.get("Alive")}


class ShareReporter:
    """A playing real-time session's side (its actor's play loop): :meth:`tick` after each call of steps sends a
    report to ``registry`` (its ``realtime(node, key, threads)``, answering ``(threads on the node, the node's
    CPUs or None)``) at most every :data:`SHARE_REFRESH_S` and none while the last is unanswered; each answer calls
    ``apply`` with the share (:func:`~hybridmpm.service.capacity.share_of`) in Ray's thread, so the play loop never
    waits on the registry. :meth:`stop` reports that the session stopped. A registry that fails is left out (the
    share stays as it was) until the next play."""

    def __init__(self, registry: Any, node: str, key: str, threads: int, apply: Callable[[float], None], clock: Callable[[], float] = time.monotonic) -> None:
        self.registry, self.node, self.key, self.threads, self.apply, self.clock = registry, node, key, int(threads), apply, clock
        self.sent = -float("inf")
        self.pending: Any = None  # the unanswered report's future
        self.failed = False

    def tick(self) -> None:
        """Report when :data:`SHARE_REFRESH_S` passed since the last report and it was answered. Never blocks."""
        now = self.clock()
        if self.failed or now - self.sent < SHARE_REFRESH_S or (self.pending is not None and not self.pending.done()):
            return
        self.sent = now
        try:
            self.pending = self.registry.realtime.remote(self.node, self.key, self.threads).future()
        except Exception:  # noqa: BLE001 - no share beats no play
            self.failed = True
            return
        self.pending.add_done_callback(self._answered)

    def _answered(self, fut: Any) -> None:
        try:
            threads, cpus = fut.result()
            if cpus:
                self.apply(share_of(threads, cpus))
        except Exception as e:  # noqa: BLE001 - the registry restarting, or gone: the share stays
            log.debug("real-time share of %s…: %s", self.key[:SHOWN_KEY_CHARS], e)

    def stop(self) -> None:
        """The session stopped playing: its report leaves the node (not waited for)."""
        with contextlib.suppress(Exception):
            self.registry.realtime.remote(self.node, self.key, 0)


__all__ = ["SHARE_EXPIRE_S", "SHARE_REFRESH_S", "NodeLoads", "ShareReporter", "node_cpus"]
