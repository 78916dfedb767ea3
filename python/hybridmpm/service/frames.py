"""The binary frame of the WebSocket stream (little-endian, 32-byte header).

=======  ======  ===========================================================
offset   type    field
=======  ======  ===========================================================
0        4s      magic ``b"HMPF"``
4        u16     version (1)
6        u8      dim (2 or 3)
7        u8      flags: bit1 controlled, bit2 neural solver (bit0 reserved: quantised)
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
SOLVER_CODES = {"mpm": 0, "neural": 1}
assert HEADER_SIZE == 32


@dataclass
class FrameHeader:
    dim: int
    frame: int
    n: int
    time: float
    solver: str
    controlled: bool
    control_frame: int


def encode_frame(positions: np.ndarray, frame: int, time: float, solver: str, controlled: bool = False, control_frame: int = 0) -> bytes:
    """One binary frame: header + ``positions`` float32 [n, dim] little-endian."""
    pos = np.ascontiguousarray(positions, "<f4")
    n, dim = pos.shape
    code = SOLVER_CODES.get(solver, 0)
    flags = (FLAG_CONTROLLED if controlled else 0) | (FLAG_NEURAL if code == 1 else 0)
    head = HEADER.pack(MAGIC, VERSION, dim, flags, int(frame) & 0xFFFFFFFF, n, float(time), code, int(bool(controlled)), 0, int(control_frame) & 0xFFFFFFFF)
    return head + pos.tobytes()


def frame_message(fr: Frame, control_frame: int = 0) -> bytes:
    """What a session's viewers get of simulator frame ``fr`` (:class:`hybridmpm.sim.Frame`):
    its binary frame (:func:`encode_frame`), ``control_frame`` frames into a
    control (0 when not controlled). The one place both backends encode a frame for a stream."""
    return encode_frame(fr.positions, fr.frame_index, fr.time, fr.solver, fr.controlled, control_frame)


def decode_frame(data: bytes) -> tuple[FrameHeader, np.ndarray]:
    """Parse a binary frame: its header and positions float32 [n, dim] (a test and client helper)."""
    if len(data) < HEADER_SIZE:
        raise ValueError("frame: shorter than its header")
    magic, version, dim, _flags, frame, n, t, code, controlled, _pad, cframe = HEADER.unpack_from(data)
    if magic != MAGIC or version != VERSION:
        raise ValueError("frame: bad magic or version")
    pos = np.frombuffer(data, "<f4", n * dim, HEADER_SIZE).reshape(n, dim)
    return FrameHeader(dim, frame, n, t, "neural" if code == 1 else "mpm", bool(controlled), cframe), pos


__all__ = ["FLAG_CONTROLLED", "FLAG_NEURAL", "HEADER", "HEADER_SIZE", "MAGIC", "VERSION", "FrameHeader", "decode_frame", "encode_frame", "frame_message"]
