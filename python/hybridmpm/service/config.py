"""Settings of the service (limits, timeouts, caps), from arguments or the environment."""

from __future__ import annotations

import os
from dataclasses import dataclass, field, fields

from hybridmpm.errors import InvalidInputError

#: Environment variables read by :meth:`ServiceConfig.from_env` (``HMPM_`` + the field name, upper case).
ENV_PREFIX = "HMPM_"


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

    def __post_init__(self) -> None:
        for name in ("max_sessions", "compute_threads", "max_controls", "max_json_bytes", "max_checkpoint_bytes", "max_frames", "max_control_frames"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise InvalidInputError(f"{name}: must be an integer >= 1, got {v!r}", name)
        for name in ("idle_ttl_s", "send_timeout_s", "max_fps"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 < float(v) < 1e9):
                raise InvalidInputError(f"{name}: must be a positive number, got {v!r}", name)
        if self.reap_interval_s is None:
            self.reap_interval_s = min(30.0, self.idle_ttl_s / 2)
        self.allowed_origins = tuple(self.allowed_origins)

    @classmethod
    def from_env(cls, **overrides: object) -> ServiceConfig:
        """Defaults, then ``HMPM_<FIELD>`` environment variables
        (``HMPM_ALLOWED_ORIGINS`` comma-separated), then ``overrides`` (None ignored)."""
        kw: dict[str, object] = {}
        for f in fields(cls):
            raw = os.environ.get(ENV_PREFIX + f.name.upper())
            if raw is None or raw == "":
                continue
            try:
                if f.name == "allowed_origins":
                    kw[f.name] = tuple(o.strip() for o in raw.split(",") if o.strip())
                elif f.name in ("idle_ttl_s", "reap_interval_s", "send_timeout_s", "max_fps"):
                    kw[f.name] = float(raw)
                else:
                    kw[f.name] = int(raw)
            except ValueError:
                raise InvalidInputError(f"{f.name}: {ENV_PREFIX}{f.name.upper()}={raw!r} is not a number", f.name) from None
        kw.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**kw)  # type: ignore[arg-type]


__all__ = ["ENV_PREFIX", "ServiceConfig"]
