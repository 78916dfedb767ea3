"""The process's memory budget (one ledger for every allocation that scales
with frames or particles) and a session's recording of its recent frames,
which takes from it as it grows."""

from __future__ import annotations

import collections
import contextlib
import math
import threading
from collections.abc import Iterator
from typing import Any

import numpy as np

from hybridmpm.limits import human
from hybridmpm.render.surface_field import MARGIN as SURFACE_MARGIN


class BudgetFullError(Exception):
    """The memory budget cannot hold an allocation (→ 503 with ``Retry-After``)."""

    def __init__(self, what: str, nbytes: int, used: int, total: int) -> None:
        super().__init__(f"{what} would need {human(nbytes)}; the server holds {human(used)} of its memory budget of {human(total)}; retry later")
        self.what, self.nbytes = what, nbytes


class MemoryBudget:
    """One memory budget for the process [bytes]: sessions, kept controls
    and the transient buffers of requests take from it before they
    allocate and give back when freed. Thread-safe (the sessions' recordings
    grow on worker threads)."""

    def __init__(self, total: int) -> None:
        self.total = int(total)
        self.used = 0
        self._lock = threading.Lock()

    def take(self, nbytes: float, what: str) -> int:
        """Reserve ``nbytes`` (rounded up) or raise :class:`BudgetFullError`; returns the bytes reserved."""
        n = max(0, int(math.ceil(nbytes)))
        with self._lock:
            if self.used + n > self.total:
                raise BudgetFullError(what, n, self.used, self.total)
            self.used += n
        return n

    def give(self, nbytes: int) -> None:
        with self._lock:
            self.used = max(0, self.used - int(nbytes))

    @contextlib.contextmanager
    def hold(self, nbytes: float, what: str) -> Iterator[int]:
        """Reserve ``nbytes`` for the ``with`` block (:class:`BudgetFullError` if it cannot)."""
        n = self.take(nbytes, what)
        try:
            yield n
        finally:
            self.give(n)


#: What a session's mesh download (``GET .../trajectory?format=mesh``) takes per position value of the frames it
#: meshes [bytes]: the stacked float32 trajectory (4), its validation's finiteness mask (1) and the zip of the
#: frames' surfaces with its copy (under 1). Measured with tracemalloc for 300 frames of every registered scene
#: (benchmarks/bench_mesh_memory.py, benchmarks/results/mesh_memory.json): 5.0-5.1 B per value at the peak
#: wherever the positions outweigh one frame's surface.
MESH_DOWNLOAD_BYTES_PER_VALUE = 6
#: What meshing one frame's surface takes per node of its grid [bytes] (the density field, its smoothing and
#: clipping copies, marching cubes' output; the grid: the scene's cells plus :data:`SURFACE_PAD_NODES` per axis,
#: at most): 5-40 B measured in 3D, under 20 B in 2D.
MESH_DOWNLOAD_BYTES_PER_NODE = 64
#: Nodes a frame's surface grid has per axis beyond the scene's ``n_grid`` at most (its margin on both sides).
SURFACE_PAD_NODES = 2 * SURFACE_MARGIN + 4


def mesh_download_bytes(frames: int, particles: int, dim: int, n_grid: int) -> int:
    """The memory a mesh download of ``frames`` frames of ``particles``
    particles in ``dim`` dimensions on an ``n_grid`` grid reserves [bytes]:
    :data:`MESH_DOWNLOAD_BYTES_PER_VALUE` per position value plus one
    frame's surface grid, ``(n_grid + SURFACE_PAD_NODES)^dim`` nodes at
    :data:`MESH_DOWNLOAD_BYTES_PER_NODE`."""
    values = int(frames) * int(particles) * int(dim)
    return MESH_DOWNLOAD_BYTES_PER_VALUE * values + MESH_DOWNLOAD_BYTES_PER_NODE * (int(n_grid) + SURFACE_PAD_NODES) ** int(dim)


def tree_nbytes(tree: Any) -> int:
    """Bytes of the arrays and byte strings in a state tree (dicts, lists, arrays, bytes)."""
    if isinstance(tree, dict):
        return sum(tree_nbytes(v) for v in tree.values())
    if isinstance(tree, (list, tuple)):
        return sum(tree_nbytes(v) for v in tree)
    if isinstance(tree, np.ndarray):
        return int(tree.nbytes)
    if isinstance(tree, (bytes, bytearray)):
        return len(tree)
    return 0


#: A recorded frame's rigid bodies: the bodies as given (the solver's ``params.bodies`` list itself: one object while
#: no body is added or removed), their centres float64 [B, D] [m], rotations [B, D, D] and masses [B] [kg].
RecordedBodies = tuple[list[Any], np.ndarray, np.ndarray, np.ndarray]

#: A recorded frame: frame index, positions float32 [N + B, D] [m], solver, whether controlled, the obstacles'
#: centres float64 [C, D] [m] (:attr:`~hybridmpm.sim.base.Frame.obstacle_centers`; None in a scene without obstacles)
#: and its bodies (None in a scene without them).
RecordedFrame = tuple[int, np.ndarray, str, bool, np.ndarray | None, RecordedBodies | None]


class Recording:
    """A session's latest frames for download: consecutive coarse steps (a
    frame that does not follow the last one — a reset, a restored checkpoint —
    starts it again), at most ``capacity``. The ring's memory is taken from
    the budget as it grows and kept until the session is dropped; when the
    budget cannot hold another frame the ring stops growing and drops its
    oldest frame instead. Not thread-safe: its session's core guards it."""

    def __init__(self, budget: MemoryBudget, capacity: int, r_t: int) -> None:
        self.budget = budget
        self.capacity = int(capacity)
        self.r_t = max(1, int(r_t))
        self.frames: collections.deque[RecordedFrame] = collections.deque()
        self.held = 0  # bytes taken from the budget

    def __len__(self) -> int:
        return len(self.frames)

    def clear(self) -> None:
        self.frames.clear()

    def add(
        self, frame_index: int, positions: np.ndarray, solver: str, controlled: bool, centers: np.ndarray | None = None, bodies: RecordedBodies | None = None
    ) -> None:
        if self.capacity < 1:
            return
        k = int(frame_index)
        if self.frames and k == self.frames[-1][0]:
            return  # already recorded (a step's last frame is published after it was recorded)
        if self.frames and k != self.frames[-1][0] + self.r_t:
            self.frames.clear()
        pos = np.array(positions, np.float32)
        if len(self.frames) >= self.capacity:
            self.frames.popleft()
        elif (len(self.frames) + 1) * pos.nbytes > self.held:
            try:
                self.held += self.budget.take(pos.nbytes, "recording the session's frames")
            except BudgetFullError:
                if not self.frames:
                    return
                self.frames.popleft()
        kept: RecordedBodies | None = None
        if bodies is not None:
            given, center, rotation, mass = bodies
            kept = (given, np.array(center, np.float64), np.array(rotation, np.float64), np.array(mass, np.float64))
        self.frames.append((k, pos, str(solver), bool(controlled), None if centers is None else np.array(centers, np.float64), kept))

    def last(self, count: int) -> list[RecordedFrame]:
        """The latest ``count`` frames recorded (fewer if fewer are held), oldest first."""
        n = min(max(0, int(count)), len(self.frames))
        return list(self.frames)[len(self.frames) - n :]

    def release(self) -> None:
        self.frames.clear()
        self.budget.give(self.held)
        self.held = 0


__all__ = [
    "MESH_DOWNLOAD_BYTES_PER_NODE",
    "MESH_DOWNLOAD_BYTES_PER_VALUE",
    "SURFACE_PAD_NODES",
    "BudgetFullError",
    "MemoryBudget",
    "RecordedBodies",
    "RecordedFrame",
    "Recording",
    "mesh_download_bytes",
    "tree_nbytes",
]
