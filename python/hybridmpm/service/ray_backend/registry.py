"""The registry of a Ray cluster's sessions (one actor per namespace): the
session cap and the per-client quota over every front end, the lock of
the cluster's local store, and the real-time sessions playing on each node
(their shares, :mod:`~hybridmpm.service.ray_backend.shares`)."""

from __future__ import annotations

import contextlib
import threading
import time
from typing import Any

import ray

from hybridmpm.errors import InvalidInputError
from hybridmpm.service.ray_backend.shares import NodeLoads, node_cpus
from hybridmpm.service.store import SessionStore

#: A session's actor is named this + its store key (the SHA-256 of its id: the id is no actor name).
ACTOR_PREFIX = "session-"
#: The name of the :class:`Registry` actor in the namespace.
REGISTRY_NAME = "registry"
#: Seconds between the registry's looks for sessions whose actor is gone, and how old such an entry must be.
REGISTRY_PRUNE_S = 30.0
REGISTRY_GRACE_S = 120.0


class Registry:
    """The cluster's sessions (their keys and client addresses), one actor
    per namespace: :meth:`reserve` enforces the session cap and the
    per-client quota for every front end at once. Built again after a
    restart from the session actors alive in the namespace; an entry whose
    actor is gone is dropped after :data:`REGISTRY_GRACE_S`.

    It also holds the cluster's local store (``store``, the path its first
    front end was given, and any other a front end asks for with
    :meth:`claim_store`): the store's lock (:meth:`SessionStore.claim`) is the
    registry's, taken again when Ray restarts it, so a plain server (or
    another cluster's front end) started on that store is refused while the
    cluster lives, and the cluster's front ends share it.

    Real-time sessions report to it while they play (:meth:`realtime`); that soft state is not rebuilt after a
    restart: the reports renew it within :data:`~hybridmpm.service.ray_backend.shares.SHARE_REFRESH_S`."""

    def __init__(self, store: str | None = None, namespace: str = "") -> None:
        self.held: dict[str, tuple[str, float]] = {}
        self.namespace = namespace
        self.stores: dict[str, SessionStore] = {}
        self.loads = NodeLoads()
        self.cpus: dict[str, float] = {}  # node id -> the CPUs it offers (asked of the cluster for a node not seen yet)
        if store is not None:
            self.claim_store(store)  # refused: the front end's own call says why
        now = time.monotonic()
        with contextlib.suppress(Exception):
            for name in ray.util.list_named_actors():
                if isinstance(name, str) and name.startswith(ACTOR_PREFIX):
                    client = ""
                    with contextlib.suppress(Exception):
                        out: Any = ray.get(ray.get_actor(name).client.remote(), timeout=5)
                        client = out[1] if out[0] == "ok" else ""
                    self.held[name[len(ACTOR_PREFIX) :]] = (client, now)
        threading.Thread(target=self._prune_forever, name="prune", daemon=True).start()

    def reserve(self, key: str, client: str, max_sessions: int, max_per_client: int, restoring: bool = False) -> str | None:
        """Count ``key`` for ``client``: None, or ``"cap"`` (the cluster holds
        ``max_sessions``) or ``"quota"`` (the client holds ``max_per_client``;
        not for a session ``restoring`` from the store). A key already
        counted is accepted again."""
        if key in self.held:
            return None
        if len(self.held) >= max_sessions:
            return "cap"
        if not restoring and sum(1 for c, _ in self.held.values() if c == client) >= max_per_client:
            return "quota"
        self.held[key] = (client, time.monotonic())
        return None

    def release(self, key: str) -> None:
        """``key`` leaves the cluster: no longer counted, nor its real-time report."""
        self.held.pop(key, None)
        self.loads.drop(key)

    def realtime(self, node: str, key: str, threads: int) -> tuple[int, float | None]:
        """Session ``key`` plays real time on ``node`` (a node id) with ``threads`` MPM threads (0: it stopped,
        :meth:`NodeLoads.report <hybridmpm.service.ray_backend.shares.NodeLoads.report>`): ``(the threads the
        node's playing real-time sessions step on, the CPUs the node offers, or None when the cluster does not
        know it)``."""
        total = self.loads.report(node, key, threads)
        if node not in self.cpus:
            with contextlib.suppress(Exception):
                self.cpus = node_cpus()
        return total, self.cpus.get(node)

    def claim_store(self, url: str) -> str | None:
        """Hold the store at ``url`` for this cluster (a no-op for a store
        that is not a local directory, or one already held): None, or why it
        is refused (another server holds it)."""
        if url in self.stores:
            return None
        store = SessionStore(url)
        try:
            store.claim(f"the Ray registry of namespace {self.namespace!r}")
        except InvalidInputError as e:
            return str(e)
        self.stores[url] = store
        return None

    def count(self) -> int:
        return len(self.held)

    def _prune_forever(self) -> None:
        while True:
            time.sleep(REGISTRY_PRUNE_S)
            with contextlib.suppress(Exception):
                alive = {n[len(ACTOR_PREFIX) :] for n in ray.util.list_named_actors() if isinstance(n, str) and n.startswith(ACTOR_PREFIX)}
                now = time.monotonic()
                for key, (_, since) in list(self.held.items()):
                    if key not in alive and now - since > REGISTRY_GRACE_S:
                        self.held.pop(key, None)


__all__ = ["ACTOR_PREFIX", "REGISTRY_GRACE_S", "REGISTRY_NAME", "REGISTRY_PRUNE_S", "Registry"]
