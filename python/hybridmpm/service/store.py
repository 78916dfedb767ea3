"""Durable sessions: each session's checkpoint (the npz + JSON of
:mod:`hybridmpm.service.checkpoint`, no pickle) in a store — a directory or
any fsspec URL — so that a restarted server brings its sessions back.

A record is named by the SHA-256 of its session id (its *key*): the store
never holds the id itself, so reading the store does not let anyone reach a
session; only a client that holds the id finds its record again (the server
hashes the id of each request). The checkpoint's ``meta`` holds what rebuilds
the session (scene, seed, solver, r_c), the client address (quotas) and the
wall time it was last used (expiry). Its state is the simulator's
``state()`` plus, for a simulator at ``r_p < 1``, the clusters of its
downsampled scene (:data:`CLUSTERS_KEY`): a restored session rebuilds its
scene from them instead of running the k-means again, which in a fresh
process costs about 3 s (scikit-learn's import and the fit) of the time from
a crash to the session answering.

Writes are atomic:

* a local directory: ``<key>.npz`` is written as a temporary file in the same
  directory (``.<key>.<random>.tmp``), flushed to disk, then renamed over the
  old one (``os.replace``); a crash in the middle leaves the previous save
  and a temporary file that the next start removes;
* any other fsspec store (no atomic rename): each save is a new numbered
  object ``<key>/<n>.npz``, then the pointer ``<key>/HEAD`` (the name of the
  newest complete object) is written last; the previous object is kept until
  the next save, and a reader that cannot load the object HEAD names falls
  back to the newest numbered object that loads.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import re
import secrets
import stat
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError
from hybridmpm.files import FILE_KINDS, read_regular_file
from hybridmpm.mpm import INTEGRATORS
from hybridmpm.scenes.core import Clusters
from hybridmpm.service import checkpoint as ckpt

log = logging.getLogger("hybridmpm.service")

#: Environment variable for tests: the Nth save of the process (1-based)
#: writes part of its temporary file, then the process kills itself (SIGKILL).
TEAR_ENV = "HYBRIDMPM_STORE_TEAR_AT_SAVE"
#: Characters of a key shown in logs.
SHOWN_KEY_CHARS = 8
#: The ``meta`` keys a stored session has besides the checkpoint's own (scene, seed, solver, r_c).
STORE_META = ("last_used_at", "client")
#: The key of a record's state that holds the downsampled scene's clusters (labels, boundary_labels).
CLUSTERS_KEY = "__clusters__"
_KEY = re.compile(r"^[0-9a-f]{64}$")
_NUMBERED = re.compile(r"^(\d{12})\.npz$")


def session_key(sid: str) -> str:
    """The store's name for session ``sid`` (SHA-256 hex; the id itself is never stored)."""
    return hashlib.sha256(sid.encode()).hexdigest()


@dataclass
class StoredSession:
    """One record read back from the store: what rebuilds the session and its state."""

    key: str
    scene: str
    seed: int
    solver: str
    r_c: float
    last_used_at: float
    client: str
    state: dict[str, Any]
    nbytes: int
    n_grid: int | None = None
    integrator: str | None = None

    def expired(self, ttl: float) -> bool:
        """Idle for more than ``ttl`` seconds of wall time since its last use
        (the record-expiry rule of both backends; a live session's is
        :meth:`SessionCore.expired <hybridmpm.service.core.SessionCore.expired>`)."""
        return time.time() - self.last_used_at > ttl


def _bad(key: str, msg: str) -> InvalidInputError:
    return InvalidInputError(f"store: session {key[:SHOWN_KEY_CHARS]}…: {msg}", "checkpoint")


def parse_record(key: str, data: bytes, max_bytes: int) -> StoredSession:
    """A stored checkpoint → :class:`StoredSession`; :class:`InvalidInputError`
    naming the field (``checkpoint``, ``meta.<name>``) for a malformed one."""
    state, meta = ckpt.loads(data, max_bytes)
    want: dict[str, tuple[type, ...]] = {
        "scene": (str,),
        "seed": (int,),
        "solver": (str,),
        "r_c": (int, float),
        "last_used_at": (int, float),
        "client": (str,),
    }
    for name, types in want.items():
        v = meta.get(name)
        if isinstance(v, bool) or not isinstance(v, types):
            raise _bad(key, f"meta.{name}: missing or not a {' or '.join(t.__name__ for t in types)} (got {v!r})")
    n_grid = meta.get("n_grid")  # records of sessions on the scene's grid (and older records) have none
    if n_grid is not None and (isinstance(n_grid, bool) or not isinstance(n_grid, int) or not 16 <= n_grid <= 4096):
        raise _bad(key, f"meta.n_grid: not an integer in [16, 4096] (got {n_grid!r})")
    integrator = meta.get("integrator")  # records of sessions on the scene's integrator (and older records) have none
    if integrator is not None and integrator not in INTEGRATORS:
        raise _bad(key, f"meta.integrator: not one of {', '.join(map(repr, INTEGRATORS))} (got {integrator!r})")
    return StoredSession(
        key,
        meta["scene"],
        int(meta["seed"]),
        meta["solver"],
        float(meta["r_c"]),
        float(meta["last_used_at"]),
        meta["client"],
        state,
        len(data),
        n_grid,
        integrator,
    )


def record_state(sim: Any) -> dict[str, Any]:
    """What a record holds of simulator ``sim``: its ``state()``, plus its
    downsampled scene's clusters under :data:`CLUSTERS_KEY` when it runs at
    ``r_p < 1``."""
    state = dict(sim.state())
    c: Clusters | None = getattr(sim.scene, "clusters", None)
    if c is not None:
        state[CLUSTERS_KEY] = {"labels": c.labels, "boundary_labels": c.boundary_labels}
    return state


def rebuild(rec: StoredSession, threads: int = 1) -> tuple[Any, dict[str, Any]]:
    """The simulator of a stored session at its saved state, and its initial
    state (for a reset): built with the record's clusters (no k-means) on
    ``threads`` MPM threads, then
    restored. Blocks. Raises what :func:`~hybridmpm.sim.make_simulator` and
    ``restore`` raise (:class:`InvalidInputError` naming the field) for a
    record that does not fit its scene."""
    from hybridmpm.sim import make_simulator  # the simulators import torch-free but heavy modules; the store alone does not need them

    state = dict(rec.state)
    raw = state.pop(CLUSTERS_KEY, None)
    clusters = None
    if raw is not None:
        if not isinstance(raw, dict) or set(raw) != {"labels", "boundary_labels"}:
            raise InvalidInputError(f"store: session {rec.key[:SHOWN_KEY_CHARS]}…: {CLUSTERS_KEY} must hold labels and boundary_labels", "checkpoint")
        clusters = Clusters(np.asarray(raw["labels"]), np.asarray(raw["boundary_labels"]))
    sim = make_simulator(
        rec.scene, rec.solver, r_c=rec.r_c, seed=rec.seed, threads=threads, nn_threads=1, clusters=clusters, n_grid=rec.n_grid, integrator=rec.integrator
    )
    initial = sim.state()
    sim.restore(state)
    return sim, initial


class SessionStore:
    """The records of one store (``url``: a directory or an fsspec URL).
    :meth:`open` checks that it can be written (:class:`InvalidInputError`,
    field ``store``, naming the path and the reason). Methods block: call them
    off the event loop."""

    def __init__(self, url: str) -> None:
        import fsspec
        from fsspec.implementations.local import LocalFileSystem

        self.url = url
        try:
            fs, path = fsspec.core.url_to_fs(url)
        except (ValueError, ImportError, OSError) as e:
            raise InvalidInputError(f"store: cannot open {url!r} ({type(e).__name__}: {e})", "store") from None
        self.fs = fs
        self.local = isinstance(fs, LocalFileSystem)
        self.root = os.path.abspath(path) if self.local else path.rstrip("/")
        self._seq: dict[str, int] = {}
        self.saves = 0
        self._lock_fd: int | None = None  # the held claim (:meth:`claim`)

    # ------------------------------------------------------------ setup
    def open(self, clean_after_s: float | None = 0.0) -> SessionStore:
        """Create the store if needed, check it is writable, remove temporary
        files of torn writes older than ``clean_after_s`` seconds (None: none;
        a store that several processes write at once keeps the recent ones,
        which may be saves in progress). Raises :class:`InvalidInputError`
        (field ``store``) when it cannot be written."""
        probe = f".probe-{secrets.token_hex(4)}"
        try:
            if self.local:
                os.makedirs(self.root, exist_ok=True)
                p = os.path.join(self.root, probe)
                with open(p, "wb") as f:
                    f.write(b"ok")
                os.remove(p)
                min_age = -1.0 if clean_after_s is None else float(clean_after_s)
                for name in os.listdir(self.root) if min_age >= 0 else ():
                    if name.startswith(".") and name.endswith(".tmp"):
                        with contextlib.suppress(OSError):
                            tmp = os.path.join(self.root, name)
                            if time.time() - os.stat(tmp).st_mtime < min_age:
                                continue
                            os.remove(tmp)
                            log.info("store: removed %s (a save that did not finish)", name[:12])
            else:
                self.fs.makedirs(self.root, exist_ok=True)
                self.fs.pipe_file(f"{self.root}/{probe}", b"ok")
                self.fs.rm_file(f"{self.root}/{probe}")
        except OSError as e:
            raise InvalidInputError(f"store: cannot write to {self.url!r} ({type(e).__name__}: {e.strerror or e})", "store") from None
        return self

    def claim(self, holder: str = "") -> None:
        """Hold this (local) store for this process until :meth:`release` or
        the process ends: one server writes a store, and a second one started
        on it is refused with :class:`InvalidInputError` (field ``store``)
        naming the holder (its pid, then ``holder``, at most 100 characters).
        An exclusive ``flock`` on ``.lock`` in the store; the OS drops it when
        the holder dies, even by SIGKILL. ``.lock`` must be a regular file of
        its own: it is opened without following links, and a symbolic or hard
        link, a directory, a FIFO or a device there is refused
        (:class:`InvalidInputError`, field ``store``) before anything is
        written. Stores on other filesystems (fsspec
        URLs) cannot be locked this way and are not. On a Ray cluster the
        namespace's registry actor holds it for every front end
        (:class:`~hybridmpm.service.ray_backend.registry.Registry`)."""
        if not self.local or self._lock_fd is not None:
            return
        import fcntl

        fd = self._open_lock()
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            try:
                held_by = os.read(fd, 128).decode("utf-8", "replace").strip() or "?"
            finally:
                os.close(fd)
            raise InvalidInputError(
                f"store: {self.url!r} is in use by another server (pid {held_by}); one server writes a store (front ends share one only with --backend ray)",
                "store",
            ) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}{', ' + holder[:100] if holder else ''}".encode())
        self._lock_fd = fd

    def _open_lock(self) -> int:
        """The store's ``.lock``, opened (created if missing) for reading and
        writing without following a symbolic link and without blocking, and
        kept only if it is a regular file with no other name (a hard link
        would let the claim write into a file outside the store). Raises
        :class:`InvalidInputError` (field ``store``) naming what it is instead."""
        path = os.path.join(self.root, ".lock")
        flags = os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0)
        try:
            fd = os.open(path, flags, 0o644)
        except OSError as e:
            try:
                mode = os.lstat(path).st_mode
                kind = "a symbolic link" if stat.S_ISLNK(mode) else FILE_KINDS.get(stat.S_IFMT(mode), f"not a file the server can open ({e.strerror or e})")
            except OSError:
                kind = f"not a file the server can open ({e.strerror or e})"
            raise InvalidInputError(f"store: {path} is {kind}; the claim of a store must be a regular file (remove it)", "store") from None
        try:
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode) or st.st_nlink != 1:
                kind = "a hard link to another file" if stat.S_ISREG(st.st_mode) else FILE_KINDS.get(stat.S_IFMT(st.st_mode), "not a regular file")
                raise InvalidInputError(f"store: {path} is {kind}; the claim of a store must be a regular file (remove it)", "store")
        except BaseException:
            os.close(fd)
            raise
        return fd

    def release(self) -> None:
        """Let another server claim the store (:meth:`claim`)."""
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    # ------------------------------------------------------------ write
    def write(self, key: str, data: bytes) -> None:
        """Save ``data`` as ``key``'s checkpoint, atomically (see the module's notes)."""
        assert _KEY.match(key)
        self.saves += 1
        tear = os.environ.get(TEAR_ENV)
        torn = tear is not None and tear.isdigit() and int(tear) == self.saves
        if self.local:
            tmp = os.path.join(self.root, f".{key}.{secrets.token_hex(4)}.tmp")
            try:
                with open(tmp, "wb") as f:
                    if torn:
                        f.write(data[: len(data) // 2])
                        f.flush()
                        os.fsync(f.fileno())
                        _die()
                    f.write(data)
                    f.flush()
                    os.fsync(f.fileno())
                os.replace(tmp, os.path.join(self.root, key + ".npz"))
            except BaseException:
                with contextlib.suppress(OSError):
                    os.remove(tmp)
                raise
            with contextlib.suppress(OSError):  # the rename itself made durable
                fd = os.open(self.root, os.O_RDONLY)
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)
            return
        d = f"{self.root}/{key}"
        seq = self._seq.get(key)
        if seq is None:
            seq = max(self._numbered(key), default=0)
        seq += 1
        name = f"{seq:012d}.npz"
        if torn:
            self.fs.pipe_file(f"{d}/{name}", data[: len(data) // 2])
            _die()
        self.fs.pipe_file(f"{d}/{name}", data)
        self.fs.pipe_file(f"{d}/HEAD", name.encode())
        self._seq[key] = seq
        for old in self._numbered(key):
            if old < seq - 1:
                with contextlib.suppress(OSError, FileNotFoundError):
                    self.fs.rm_file(f"{d}/{old:012d}.npz")

    def has(self, key: str) -> bool:
        """Whether ``key`` has a record (not whether it loads)."""
        assert _KEY.match(key)
        if self.local:
            return os.path.exists(os.path.join(self.root, key + ".npz"))
        try:
            return bool(self.fs.exists(f"{self.root}/{key}/HEAD"))
        except OSError:
            return False

    def delete(self, key: str) -> None:
        """Forget ``key``'s record (a deleted or expired session)."""
        self._seq.pop(key, None)
        with contextlib.suppress(OSError, FileNotFoundError):
            if self.local:
                os.remove(os.path.join(self.root, key + ".npz"))
            else:
                self.fs.rm(f"{self.root}/{key}", recursive=True)

    # ------------------------------------------------------------ read
    def keys(self) -> list[str]:
        if self.local:
            return sorted(n[:-4] for n in os.listdir(self.root) if n.endswith(".npz") and _KEY.match(n[:-4]))
        out = []
        for p in self.fs.ls(self.root, detail=False):
            name = str(p).rstrip("/").rsplit("/", 1)[-1]
            if _KEY.match(name):
                out.append(name)
        return sorted(out)

    def _numbered(self, key: str) -> list[int]:
        try:
            names = [str(p).rstrip("/").rsplit("/", 1)[-1] for p in self.fs.ls(f"{self.root}/{key}", detail=False)]
        except (OSError, FileNotFoundError):
            return []
        return sorted(int(m.group(1)) for n in names if (m := _NUMBERED.match(n)))

    def candidates(self, key: str, max_bytes: int) -> Iterator[bytes]:
        """The saves of ``key`` to try, best first (local: the one file, which
        must be a regular file of at most ``max_bytes``, checked on the open
        file before reading — a FIFO, a device or a link to one is refused
        without blocking; other stores: the object HEAD names, then the
        numbered objects newest first)."""
        if self.local:
            yield read_regular_file(os.path.join(self.root, key + ".npz"), max_bytes, "checkpoint", "store record")
            return
        d = f"{self.root}/{key}"
        tried = set()
        with contextlib.suppress(OSError, FileNotFoundError, UnicodeDecodeError):
            head = self.fs.cat_file(f"{d}/HEAD").decode().strip()
            m = _NUMBERED.match(head)
            if m:
                tried.add(int(m.group(1)))
                with contextlib.suppress(OSError, FileNotFoundError):
                    yield self.fs.cat_file(f"{d}/{head}")
        for seq in reversed(self._numbered(key)):
            if seq not in tried:
                with contextlib.suppress(OSError, FileNotFoundError):
                    yield self.fs.cat_file(f"{d}/{seq:012d}.npz")

    def load(self, key: str, max_bytes: int) -> StoredSession:
        """The newest save of ``key`` that loads; :class:`InvalidInputError`
        (naming the field) when none does."""
        err: InvalidInputError | None = None
        try:
            for data in self.candidates(key, max_bytes):
                try:
                    rec = parse_record(key, data, max_bytes)
                except InvalidInputError as e:
                    err = e
                    continue
                if not self.local:
                    self._seq[key] = max(self._numbered(key), default=0)
                return rec
        except OSError as e:
            raise _bad(key, f"checkpoint: cannot read ({type(e).__name__})") from None
        except InvalidInputError as e:  # a local record that is not a regular file, or too large
            raise _bad(key, str(e)) from None
        if err is not None:
            raise _bad(key, str(err)) if not str(err).startswith("store:") else err
        raise _bad(key, "checkpoint: no save found")


def load_unexpired(store: SessionStore, key: str, max_bytes: int, ttl: float) -> StoredSession | None:
    """``key``'s record (:meth:`SessionStore.load`; its :class:`InvalidInputError`
    raised), or None when it is expired (:meth:`StoredSession.expired`: idle
    for more than ``ttl`` seconds), which is removed. Blocks: the store's I/O."""
    rec = store.load(key, max_bytes)
    if not rec.expired(ttl):
        return rec
    store.delete(key)
    log.info("store: session %s… expired while it was not running; removed", key[:SHOWN_KEY_CHARS])
    return None


def _die() -> None:
    """A crash in the middle of a save (tests: :data:`TEAR_ENV`)."""
    import signal

    log.error("store: %s: killing the process in the middle of a save", TEAR_ENV)
    os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(60)


__all__ = ["STORE_META", "TEAR_ENV", "SessionStore", "StoredSession", "load_unexpired", "parse_record", "session_key"]
