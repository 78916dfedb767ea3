"""The binary frame of the WebSocket stream (little-endian, 32-byte header).

=======  ======  ===========================================================
offset   type    field
=======  ======  ===========================================================
0        4s      magic ``b"HMPF"``
4        u16     version (1)
6        u8      dim (2 or 3)
7        u8      flags: bit1 controlled, bit2 neural solver, bit3 bodies follow (bit0 reserved: quantised)
8        u32     frame number (frames of ``dt_frame`` since the initial condition)
12       u32     particle count ``n`` (fluid, then boundary particles)
16       f64     simulated time [s]
24       u8      solver: 0 MPM, 1 neural
25       u8      controlled: 1 if a control forcing acted during the step
26       u16     padding (0)
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
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import TYPE_CHECKING

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
FLAGS_KNOWN = FLAG_CONTROLLED | FLAG_NEURAL | FLAG_BODIES
SOLVER_CODES = {"mpm": 0, "neural": 1}
COUNT = struct.Struct("<I")
assert HEADER_SIZE == 32


@dataclass
class FrameHeader:
    """A decoded frame's header; ``body_center`` float32 [B, dim] [m] and
    ``body_rotation`` float32 [B, dim, dim] when bodies follow the positions
    (flag bit3), else None."""

    dim: int
    frame: int
    n: int
    time: float
    solver: str
    controlled: bool
    control_frame: int
    body_center: np.ndarray | None = None
    body_rotation: np.ndarray | None = None


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
) -> bytes:
    """One binary frame: header + ``positions`` float32 [n, dim] little-endian
    [m], then, with ``body_center`` [B, dim] [m] and ``body_rotation`` [B,
    dim, dim] of B ≥ 1 bodies, the bodies' block (flag bit3; any float dtype,
    written as float32). Without bodies (None, or B = 0) the bytes are the
    frame's as before bodies existed. Raises ValueError for body arrays of
    another shape (naming them)."""
    pos = np.ascontiguousarray(positions, "<f4")
    n, dim = pos.shape
    poses = body_poses(body_center, body_rotation, dim)
    code = SOLVER_CODES.get(solver, 0)
    flags = (FLAG_CONTROLLED if controlled else 0) | (FLAG_NEURAL if code == 1 else 0) | (FLAG_BODIES if poses is not None else 0)
    head = HEADER.pack(MAGIC, VERSION, dim, flags, int(frame) & 0xFFFFFFFF, n, float(time), code, int(bool(controlled)), 0, int(control_frame) & 0xFFFFFFFF)
    if poses is None:
        return head + pos.tobytes()
    return head + pos.tobytes() + COUNT.pack(len(poses)) + poses.tobytes()


def frame_message(fr: Frame, control_frame: int = 0) -> bytes:
    """What a session's viewers get of simulator frame ``fr`` (:class:`hybridmpm.sim.Frame`):
    its binary frame (:func:`encode_frame`, with the bodies' poses when it
    holds bodies), ``control_frame`` frames into a control (0 when not
    controlled). The one place both backends encode a frame for a stream."""
    return encode_frame(fr.positions, fr.frame_index, fr.time, fr.solver, fr.controlled, control_frame, fr.body_center, fr.body_rotation)


def decode_frame(data: bytes | bytearray | memoryview) -> tuple[FrameHeader, np.ndarray]:
    """Parse a binary frame: its header (with the bodies' poses when flag
    bit3 says they follow) and positions float32 [n, dim] [m] (a test and
    client helper). Raises TypeError for data that is not bytes-like and
    ValueError, saying what is wrong, for a frame that is short, has a bad
    magic, version, dim, solver or flag bits, or whose length is not what its
    header (and body count) says."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TypeError(f"frame: expected bytes, got {type(data).__name__}")
    data = bytes(data)
    if len(data) < HEADER_SIZE:
        raise ValueError(f"frame: {len(data)} bytes, shorter than its {HEADER_SIZE}-byte header")
    magic, version, dim, flags, frame, n, t, code, controlled, _pad, cframe = HEADER.unpack_from(data)
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
    "HEADER",
    "HEADER_SIZE",
    "MAGIC",
    "VERSION",
    "FrameHeader",
    "body_poses",
    "decode_frame",
    "encode_frame",
    "frame_message",
]
