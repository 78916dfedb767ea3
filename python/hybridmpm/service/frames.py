"""The binary frame of the WebSocket stream (little-endian, 32-byte header).

=======  ======  ===========================================================
offset   type    field
=======  ======  ===========================================================
0        4s      magic ``b"HMPF"``
4        u16     version (1)
6        u8      dim (2 or 3)
7        u8      flags: bit1 controlled, bit2 neural solver, bit3 bodies follow, bit4 real-time
                 session (bit0 reserved: quantised)
8        u32     frame number (frames of ``dt_frame`` since the initial condition)
12       u32     particle count ``n`` (fluid, then boundary particles)
16       f64     simulated time [s]
24       u8      solver: 0 MPM, 1 neural
25       u8      controlled: 1 if a control forcing acted during the step
26       u16     real-time factor × 1000 (flag bit4; else padding, 0)
28       u32     control frame (frames since the control started; 0 when not controlled)
=======  ======  ===========================================================

then ``float32[n·dim]`` positions (x, y[, z] per particle). The header is a
multiple of 8 bytes so that ``new Float32Array(buf, 32, n*dim)`` is aligned.

When the session holds rigid bodies (docs/bodies.md) flag bit3 is set and
the positions are followed by ``u32`` the body count ``B`` and
``float32[B, dim + dim²]``: per body its centre of mass [m] (``dim``
numbers) and its rotation matrix row-major (``dim × dim``; its columns are
the body's axes in the world), at the frame's end, the bodies in the order
of the session's ``bodies``. A frame without bodies has neither (the bytes
every client read before bodies existed); a reader that knows no bodies
reads its positions as before and the rest is past them.

A session in real-time mode (``solver`` ``realtime``, docs/service.md
"Real-time sessions") sets flag bit4, and the ``u16`` at offset 26 holds its
real-time factor (simulated seconds per wall second of stepping on its
current rung, :meth:`hybridmpm.sim.RealtimeSimulator.realtime_info`) × 1000,
rounded and clipped to [1, 65535], or 0 while it has not been measured yet.
Without the flag those bytes are 0, as they always were.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from hybridmpm.sim import Frame

MAGIC = b"HMPF"
VERSION = 1
HEADER = struct.Struct("<4sHBBIIdBBHI")
HEADER_SIZE = HEADER.size
FLAG_CONTROLLED = 2
FLAG_NEURAL = 4
FLAG_BODIES = 8
FLAG_REALTIME = 16
FLAGS_KNOWN = FLAG_CONTROLLED | FLAG_NEURAL | FLAG_BODIES | FLAG_REALTIME
#: The real-time factor's scale in the header (its u16 holds the factor × this) and the largest value it holds.
REALTIME_SCALE = 1000
REALTIME_MAX = 0xFFFF
SOLVER_CODES = {"mpm": 0, "neural": 1}
COUNT = struct.Struct("<I")
assert HEADER_SIZE == 32


@dataclass
class FrameHeader:
    """A decoded frame's header; ``body_center`` float32 [B, dim] [m] and
    ``body_rotation`` float32 [B, dim, dim] when bodies follow the positions
    (flag bit3), else None; ``realtime`` whether the session runs in
    real-time mode (flag bit4) and ``realtime_factor`` its real-time factor
    (to 1/1000; None without the flag or while not yet measured)."""

    dim: int
    frame: int
    n: int
    time: float
    solver: str
    controlled: bool
    control_frame: int
    body_center: np.ndarray | None = None
    body_rotation: np.ndarray | None = None
    realtime: bool = False
    realtime_factor: float | None = None


def realtime_code(factor: float | None) -> int:
    """The header's u16 of a real-time session whose factor is ``factor``: ``factor`` × :data:`REALTIME_SCALE`,
    rounded, clipped to [1, :data:`REALTIME_MAX`]; 0 for None (not yet measured) or a factor that is no number."""
    if factor is None:
        return 0
    f = float(factor)
    if not np.isfinite(f):
        return REALTIME_MAX if f > 0 else 0
    return int(min(REALTIME_MAX, max(1, round(f * REALTIME_SCALE))))


def body_poses(center: np.ndarray | None, rotation: np.ndarray | None, dim: int) -> np.ndarray | None:
    """Body poses as the binary answers carry them: float32 [B, dim + dim²]
    (centre, then the rotation row-major) from ``center`` [B, dim] [m] and
    ``rotation`` [B, dim, dim]; None when either is None or B is 0. Raises
    ValueError naming ``body_center`` / ``body_rotation`` for other shapes."""
    if center is None or rotation is None:
        return None
    c, r = np.asarray(center), np.asarray(rotation)
    if c.ndim != 2 or c.shape[1] != dim:
        raise ValueError(f"body_center: expected shape [B, {dim}], got {list(c.shape)}")
    if r.shape != (len(c), dim, dim):
        raise ValueError(f"body_rotation: expected shape [{len(c)}, {dim}, {dim}], got {list(r.shape)}")
    if not len(c):
        return None
    return np.concatenate([c.astype("<f4"), r.astype("<f4").reshape(len(c), dim * dim)], axis=1)


def encode_frame(
    positions: np.ndarray,
    frame: int,
    time: float,
    solver: str,
    controlled: bool = False,
    control_frame: int = 0,
    body_center: np.ndarray | None = None,
    body_rotation: np.ndarray | None = None,
    realtime: bool = False,
    realtime_factor: float | None = None,
) -> bytes:
    """One binary frame: header + ``positions`` float32 [n, dim] little-endian
    [m], then, with ``body_center`` [B, dim] [m] and ``body_rotation`` [B,
    dim, dim] of B ≥ 1 bodies, the bodies' block (flag bit3; any float dtype,
    written as float32). Without bodies (None, or B = 0) the bytes are the
    frame's as before bodies existed. With ``realtime`` (a session in
    real-time mode) flag bit4 is set and offset 26 holds
    :func:`realtime_code` of ``realtime_factor``; without it those bytes are 0.
    Raises ValueError for body arrays of another shape (naming them)."""
    pos = np.ascontiguousarray(positions, "<f4")
    n, dim = pos.shape
    poses = body_poses(body_center, body_rotation, dim)
    code = SOLVER_CODES.get(solver, 0)
    flags = (FLAG_CONTROLLED if controlled else 0) | (FLAG_NEURAL if code == 1 else 0) | (FLAG_BODIES if poses is not None else 0)
    flags |= FLAG_REALTIME if realtime else 0
    rt = realtime_code(realtime_factor) if realtime else 0
    head = HEADER.pack(MAGIC, VERSION, dim, flags, int(frame) & 0xFFFFFFFF, n, float(time), code, int(bool(controlled)), rt, int(control_frame) & 0xFFFFFFFF)
    if poses is None:
        return head + pos.tobytes()
    return head + pos.tobytes() + COUNT.pack(len(poses)) + poses.tobytes()


def frame_message(fr: Frame, control_frame: int = 0, realtime: dict[str, Any] | None = None) -> bytes:
    """What a session's viewers get of simulator frame ``fr`` (:class:`hybridmpm.sim.Frame`):
    its binary frame (:func:`encode_frame`, with the bodies' poses when it
    holds bodies), ``control_frame`` frames into a control (0 when not
    controlled); ``realtime`` a real-time session's
    :meth:`~hybridmpm.sim.RealtimeSimulator.realtime_info` (flag bit4 and its
    ``realtime_factor``), None for any other session. The one place both
    backends encode a frame for a stream."""
    factor = None if realtime is None else realtime.get("realtime_factor")
    return encode_frame(
        fr.positions, fr.frame_index, fr.time, fr.solver, fr.controlled, control_frame, fr.body_center, fr.body_rotation, realtime is not None, factor
    )


def decode_frame(data: bytes | bytearray | memoryview) -> tuple[FrameHeader, np.ndarray]:
    """Parse a binary frame: its header (with the bodies' poses when flag
    bit3 says they follow, the real-time factor when bit4 says the session
    runs in real-time mode) and positions float32 [n, dim] [m] (a test and
    client helper). Raises TypeError for data that is not bytes-like and
    ValueError, saying what is wrong, for a frame that is short, has a bad
    magic, version, dim, solver or flag bits, or whose length is not what its
    header (and body count) says."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TypeError(f"frame: expected bytes, got {type(data).__name__}")
    data = bytes(data)
    if len(data) < HEADER_SIZE:
        raise ValueError(f"frame: {len(data)} bytes, shorter than its {HEADER_SIZE}-byte header")
    magic, version, dim, flags, frame, n, t, code, controlled, rt, cframe = HEADER.unpack_from(data)
    if magic != MAGIC or version != VERSION:
        raise ValueError(f"frame: bad magic or version ({magic!r}, {version}; expected {MAGIC!r}, {VERSION})")
    if dim not in (2, 3):
        raise ValueError(f"frame: dim {dim} (expected 2 or 3)")
    if flags & ~FLAGS_KNOWN:
        raise ValueError(f"frame: unknown flag bits {flags & ~FLAGS_KNOWN:#04x} (this reader knows {FLAGS_KNOWN:#04x})")
    if code not in SOLVER_CODES.values():
        raise ValueError(f"frame: solver code {code} (expected 0 MPM or 1 neural)")
    end = HEADER_SIZE + 4 * n * dim
    if end > len(data):
        raise ValueError(f"frame: {n} particles need {end - HEADER_SIZE} bytes of positions, {len(data) - HEADER_SIZE} follow the header")
    pos = np.frombuffer(data, "<f4", n * dim, HEADER_SIZE).reshape(n, dim)
    header = FrameHeader(dim, frame, n, t, "neural" if code == 1 else "mpm", bool(controlled), cframe)
    if flags & FLAG_REALTIME:
        header.realtime, header.realtime_factor = True, (rt / REALTIME_SCALE if rt else None)
    if not flags & FLAG_BODIES:
        if end != len(data):
            raise ValueError(f"frame: {len(data) - end} bytes after the positions and no bodies flag")
        return header, pos
    if end + COUNT.size > len(data):
        raise ValueError("frame: the bodies flag is set but the body count is missing")
    (b,) = COUNT.unpack_from(data, end)
    per = dim + dim * dim
    if b == 0 or end + COUNT.size + 4 * b * per != len(data):
        raise ValueError(f"frame: {b} bodies need {4 * b * per} bytes of poses, {len(data) - end - COUNT.size} follow the count")
    poses = np.frombuffer(data, "<f4", b * per, end + COUNT.size).reshape(b, per)
    header.body_center, header.body_rotation = poses[:, :dim], poses[:, dim:].reshape(b, dim, dim)
    return header, pos


__all__ = [
    "FLAG_BODIES",
    "FLAG_CONTROLLED",
    "FLAG_NEURAL",
    "FLAG_REALTIME",
    "FLAGS_KNOWN",
    "HEADER",
    "HEADER_SIZE",
    "MAGIC",
    "REALTIME_MAX",
    "REALTIME_SCALE",
    "VERSION",
    "FrameHeader",
    "body_poses",
    "decode_frame",
    "encode_frame",
    "frame_message",
    "realtime_code",
]
