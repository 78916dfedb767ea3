"""Settings of the service (limits, timeouts, caps), from arguments or the environment."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field, fields

from hybridmpm.errors import InvalidInputError

#: Environment variables read by :meth:`ServiceConfig.from_env`: ``HYBRIDMPM_`` + the
#: field name, upper case, except :data:`MEMORY_BUDGET_ENV`.
ENV_PREFIX = "HYBRIDMPM_"
#: The service's process-wide budget (``memory_budget``). Not ``HYBRIDMPM_MEMORY_BUDGET``:
#: that name is the engine's budget of one allocation (:data:`hybridmpm.limits.ENV_VAR`),
#: which is also this budget's default.
MEMORY_BUDGET_ENV = "HYBRIDMPM_SERVICE_MEMORY_BUDGET"
#: The names of this machine on the loopback interface: the default trusted ``Host`` values.
LOOPBACK_HOSTS = ("localhost", "127.0.0.1", "[::1]")
#: Longest error message a client is sent [characters] (longer ones are cut, with "…").
MAX_MESSAGE_CHARS = 300
#: Where sessions live (``ServiceConfig.backend``): this process, or a Ray cluster's actors.
BACKENDS = ("local", "ray")
_HOST_PORT = re.compile(r"^(?:[A-Za-z0-9.-]{1,253}|\[[0-9A-Fa-f:.]{2,45}\]):\d{1,5}$")
_NAMESPACE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
_TUPLES = ("allowed_origins", "allowed_hosts")
_STRINGS = ("store", "backend", "ray_address", "ray_namespace")
_BOOLS = ("realtime",)
#: How an environment variable spells a boolean setting (``HYBRIDMPM_REALTIME=1``), case-insensitive.
_TRUE, _FALSE = ("1", "true", "yes", "on"), ("0", "false", "no", "off")
_FLOATS = ("ray_num_cpus", "save_every_s", "idle_ttl_s", "reap_interval_s", "send_timeout_s", "max_fps", "header_timeout_s", "keep_alive_s", "body_timeout_s")


def env_name(field_name: str) -> str:
    """The environment variable of a :class:`ServiceConfig` field."""
    return MEMORY_BUDGET_ENV if field_name == "memory_budget" else ENV_PREFIX + field_name.upper()


@dataclass
class ServiceConfig:
    """Limits and timeouts of one service process.

    ``max_sessions`` sessions held at once (more → 503 with ``Retry-After``);
    ``idle_ttl_s`` a session untouched (no request, no WebSocket message, no
    streamed step) this long is removed and its sockets closed with code 4000;
    ``reap_interval_s`` how often the reaper looks (default ``min(30, ttl/2)``);
    ``compute_threads`` simulation work running at once (default: the cores);
    ``max_controls`` controls running at once over all sessions (more → 429);
    ``send_timeout_s`` a WebSocket send not done in this time closes the socket
    (1011); ``max_fps`` frames sent per second per socket at most;
    ``allowed_origins`` WebSocket ``Origin`` values accepted besides the
    page's own origin; ``max_json_bytes`` / ``max_checkpoint_bytes`` request
    body caps (413); ``max_frames`` frames per step request; ``max_control_frames``
    the longest control horizon.

    ``allowed_hosts`` the ``Host`` header values served (others → 400; a
    leading ``*.`` matches subdomains, ``"*"`` any host); empty (the
    default): the loopback names (:data:`LOOPBACK_HOSTS`) on a connection to
    a loopback address, which keeps DNS-rebinding pages out, any host on
    other addresses; ``max_sessions_per_client``
    sessions one client address may hold (more → 429 with ``Retry-After``);
    ``memory_budget`` bytes (or ``"8G"``, ``"512M"``) that sessions, kept
    controls and the transient buffers of requests may hold together (more →
    503 with ``Retry-After``; default :func:`hybridmpm.limits.memory_budget`,
    half the physical memory); ``header_timeout_s`` a connection whose
    request line and headers are not complete in this time is closed;
    ``keep_alive_s`` an idle keep-alive connection is closed after this;
    ``body_timeout_s`` a request body not received in this time answers 408;
    ``max_header_bytes`` request line and headers at most this large (uvicorn
    answers 400 beyond it).

    ``store`` a directory or fsspec URL where every session's checkpoint is
    kept (durable sessions, :mod:`hybridmpm.service.store`; None: sessions
    live in memory only); ``save_every_s`` the longest time a stepping
    session goes without a save (its stepping lost to a crash at most).

    ``backend`` where sessions live: ``"local"`` in this process (the
    default), ``"ray"`` each in a named actor of a Ray cluster
    (:mod:`hybridmpm.service.ray_backend`), so that several front ends serve
    every session; ``ray_address`` the cluster (``"auto"``: the one started
    on this machine with ``ray start``, or ``HOST:PORT`` of its head);
    ``ray_namespace`` the Ray namespace of the sessions' actors;
    ``ray_num_cpus`` the CPUs Ray reserves for each session's actor (its
    share of a core: the cluster's capacity is its CPUs divided by this).

    ``realtime`` (``serve --realtime``) sessions created without ``realtime``
    (null) run in real-time mode when they ask for the default solver with no
    ``n_grid`` or ``integrator`` (:func:`~hybridmpm.service.facts.checked_realtime`;
    docs/service.md "Real-time sessions"); off by default.

    Raises :class:`InvalidInputError` naming the field of a bad setting.
    """

    max_sessions: int = 100
    idle_ttl_s: float = 600.0
    reap_interval_s: float | None = None
    compute_threads: int = field(default_factory=lambda: os.cpu_count() or 1)
    max_controls: int = 8
    send_timeout_s: float = 10.0
    max_fps: float = 60.0
    allowed_origins: tuple[str, ...] = ()
    max_json_bytes: int = 64 * 1024
    max_checkpoint_bytes: int = 32 * 1024 * 1024
    max_frames: int = 100
    max_control_frames: int = 1000
    allowed_hosts: tuple[str, ...] = ()
    max_sessions_per_client: int = 20
    memory_budget: int | str | None = None
    header_timeout_s: float = 10.0
    keep_alive_s: float = 5.0
    body_timeout_s: float = 30.0
    max_header_bytes: int = 16 * 1024
    store: str | None = None
    save_every_s: float = 1.0
    backend: str = "local"
    ray_address: str = "auto"
    ray_namespace: str = "hybridmpm"
    ray_num_cpus: float = 0.25
    realtime: bool = False

    def __post_init__(self) -> None:
        from hybridmpm.limits import memory_budget, parse_size

        ints = ("max_sessions", "compute_threads", "max_controls", "max_json_bytes", "max_checkpoint_bytes", "max_frames", "max_control_frames")
        for name in (*ints, "max_sessions_per_client", "max_header_bytes"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise InvalidInputError(f"{name}: must be an integer >= 1, got {v!r}", name)
        for name in ("save_every_s", "idle_ttl_s", "send_timeout_s", "max_fps", "header_timeout_s", "keep_alive_s", "body_timeout_s"):
            v = getattr(self, name)
            if isinstance(v, bool) or not (isinstance(v, (int, float)) and 0 < float(v) < 1e9):
                raise InvalidInputError(f"{name}: must be a positive number, got {v!r}", name)
        if self.reap_interval_s is None:
            self.reap_interval_s = min(30.0, self.idle_ttl_s / 2)
        self.allowed_origins = tuple(self.allowed_origins)
        self.allowed_hosts = tuple(h.strip().lower() for h in self.allowed_hosts if h.strip())
        for h in self.allowed_hosts:
            if not h or "*" in h[1:] or (h.startswith("*") and h != "*" and not h.startswith("*.")):
                raise InvalidInputError(f"allowed_hosts: {h!r} is no host name (a leading '*.' or '*' alone are the only wildcards)", "allowed_hosts")
        self.memory_budget = memory_budget() if self.memory_budget is None else parse_size(self.memory_budget, "memory_budget")
        if self.backend not in BACKENDS:
            raise InvalidInputError(f"backend: must be one of {', '.join(BACKENDS)}, got {self.backend!r}", "backend")
        if not isinstance(self.ray_address, str) or not (self.ray_address == "auto" or _HOST_PORT.match(self.ray_address)):
            raise InvalidInputError(f"ray_address: must be 'auto' or HOST:PORT (e.g. 10.0.0.5:6379), got {self.ray_address!r}", "ray_address")
        if self.ray_address != "auto" and not 0 < int(self.ray_address.rsplit(":", 1)[1]) < 65536:
            raise InvalidInputError(f"ray_address: the port must be in 1..65535, got {self.ray_address!r}", "ray_address")
        if not isinstance(self.ray_namespace, str) or not _NAMESPACE.match(self.ray_namespace):
            raise InvalidInputError(f"ray_namespace: letters, digits, '-', '_' and '.', 1 to 64 of them, got {self.ray_namespace!r}", "ray_namespace")
        v = self.ray_num_cpus
        if isinstance(v, bool) or not (isinstance(v, (int, float)) and 0.0001 <= float(v) <= 1024):
            raise InvalidInputError(f"ray_num_cpus: must be a number in [0.0001, 1024], got {v!r}", "ray_num_cpus")
        self.ray_num_cpus = float(v)
        if not isinstance(self.realtime, bool):
            raise InvalidInputError(f"realtime: must be true or false, got {self.realtime!r}", "realtime")
        if self.backend == "ray" and self.store is not None and self.store.startswith("memory:"):
            raise InvalidInputError(
                "store: memory:// lives in one process; the ray backend needs a store every node reaches (a shared directory or an object store URL)", "store"
            )

    @property
    def memory_budget_bytes(self) -> int:
        """:attr:`memory_budget` in bytes."""
        assert isinstance(self.memory_budget, int)
        return self.memory_budget

    @classmethod
    def from_env(cls, **overrides: object) -> ServiceConfig:
        """Defaults, then :func:`env_name` environment variables
        (``HYBRIDMPM_ALLOWED_ORIGINS``, ``HYBRIDMPM_ALLOWED_HOSTS`` comma-separated,
        ``HYBRIDMPM_SERVICE_MEMORY_BUDGET`` a size such as ``8G``, ``HYBRIDMPM_REALTIME``
        ``1``/``0``, ``true``/``false``, ``yes``/``no`` or ``on``/``off``), then ``overrides`` (None ignored)."""
        kw: dict[str, object] = {}
        for f in fields(cls):
            raw = os.environ.get(env_name(f.name))
            if raw is None or raw == "":
                continue
            if f.name in _BOOLS:
                word = raw.strip().lower()
                if word not in (*_TRUE, *_FALSE):
                    raise InvalidInputError(f"{f.name}: {env_name(f.name)}={raw!r} is not 1/0, true/false, yes/no or on/off", f.name)
                kw[f.name] = word in _TRUE
                continue
            try:
                if f.name in _STRINGS:
                    kw[f.name] = raw
                elif f.name in _TUPLES:
                    kw[f.name] = tuple(o.strip() for o in raw.split(",") if o.strip())
                elif f.name == "memory_budget":
                    kw[f.name] = raw
                elif f.name in _FLOATS:
                    kw[f.name] = float(raw)
                else:
                    kw[f.name] = int(raw)
            except ValueError:
                raise InvalidInputError(f"{f.name}: {env_name(f.name)}={raw!r} is not a number", f.name) from None
        kw.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**kw)  # type: ignore[arg-type]


__all__ = ["BACKENDS", "ENV_PREFIX", "LOOPBACK_HOSTS", "MAX_MESSAGE_CHARS", "MEMORY_BUDGET_ENV", "ServiceConfig", "env_name"]
