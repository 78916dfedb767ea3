"""A real server in a subprocess on 127.0.0.1 for tests and benchmarks
(``hybridmpm serve --port 0``: the server binds a port the system chooses,
read back from the child's listening socket, so no other process can take it
between choosing and binding; stopped with :meth:`LiveServer.stop`)."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def listening_port(pid: int) -> int | None:
    """The TCP port process ``pid`` listens on (Linux: its socket inodes
    matched in ``/proc/PID/net/tcp``), or None while it listens on none."""
    try:
        inodes = set()
        for fd in os.listdir(f"/proc/{pid}/fd"):
            try:
                target = os.readlink(f"/proc/{pid}/fd/{fd}")
            except OSError:  # closed meanwhile
                continue
            if target.startswith("socket:["):
                inodes.add(target[len("socket:[") : -1])
        for table in ("tcp", "tcp6"):
            for line in Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]:
                f = line.split()
                if f[3] == "0A" and f[9] in inodes:  # state LISTEN
                    return int(f[1].rsplit(":", 1)[1], 16)
    except OSError:
        return None
    return None


class LiveServer:
    """``hybridmpm serve`` in a child process. ``env`` adds ``HYBRIDMPM_*`` settings
    (:meth:`ServiceConfig.from_env`; the per-client session quota is
    ``max_sessions`` unless ``env`` sets it: every request of a test comes
    from one address); ``args`` more ``serve`` arguments (``["--log-level",
    "info"]``); ``port``, ``url`` and ``ws_url`` are known once it is started
    (:meth:`start`, or entering the ``with``)."""

    def __init__(
        self,
        max_sessions: int = 100,
        ttl: float = 600.0,
        env: dict[str, str] | None = None,
        log: Path | None = None,
        args: list[str] | None = None,
    ) -> None:
        self.port = 0
        self.url = self.ws_url = ""
        cmd = [
            sys.executable,
            "-m",
            "hybridmpm",
            "serve",
            "--host",
            "127.0.0.1",
            "--port",
            "0",
            "--max-sessions",
            str(max_sessions),
            "--ttl",
            str(ttl),
            *(args or []),
        ]
        full_env = {**os.environ, "HYBRIDMPM_MAX_SESSIONS_PER_CLIENT": str(max_sessions), **(env or {})}
        self._log = open(log, "wb") if log is not None else subprocess.DEVNULL  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen(cmd, env=full_env, stdout=self._log, stderr=self._log)

    def start(self, timeout: float = 60.0) -> LiveServer:
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited with {self.proc.returncode}")
            if not self.port:
                port = listening_port(self.proc.pid)
                if port is None:
                    time.sleep(0.1)
                    continue
                self.port = port
                self.url = f"http://127.0.0.1:{port}"
                self.ws_url = f"ws://127.0.0.1:{port}"
            try:
                with urllib.request.urlopen(self.url + "/healthz", timeout=1) as r:
                    if r.status == 200:
                        return self
            except OSError:
                time.sleep(0.1)
        self.stop()
        raise RuntimeError("server did not start in time")

    def rss(self) -> int:
        """Resident memory of the server process [bytes]."""
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
        return 0

    def threads(self) -> int:
        return len(os.listdir(f"/proc/{self.proc.pid}/task"))

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        if hasattr(self._log, "close"):
            self._log.close()

    def __enter__(self) -> LiveServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


__all__ = ["LiveServer", "free_port", "listening_port"]
