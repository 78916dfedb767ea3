"""Exception hierarchy of hybridmpm.

Every error raised by the Rust core is mapped to one of these classes by the
binding (``rust/python/src/errors.rs``); input errors also subclass
:class:`ValueError` so ``except ValueError`` keeps working.
"""

from __future__ import annotations

from typing import Any

import numpy as np


class HybridMpmError(Exception):
    """Base class of every hybridmpm error."""


class InvalidInputError(HybridMpmError, ValueError):
    """An argument, array or parameter is malformed or out of range.

    Attributes
    ----------
    field:
        Name of the offending field (``"positions"``, ``"water.bulk_modulus"``, ...),
        or ``None`` when the error is not tied to one field.
    """

    def __init__(self, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.field = field


class SimulationError(HybridMpmError, RuntimeError):
    """The simulation could not advance (e.g. the state became non-finite).

    The solver's state is left exactly as it was before the failing call.

    Attributes
    ----------
    substep:
        Index (0-based) of the substep within the frame at which the failure
        was detected, or ``None``.
    """

    def __init__(self, message: str, substep: int | None = None) -> None:
        super().__init__(message)
        self.substep = substep


class CheckpointError(HybridMpmError, ValueError):
    """A checkpoint blob is malformed, truncated or from an incompatible version."""


def as_f32(name: str, value: Any) -> np.ndarray:
    """``value`` as a contiguous float32 array if it is a real floating array
    (lossless enough for positions); anything else raises
    :class:`InvalidInputError` naming ``name``."""
    arr = np.asarray(value)
    if arr.dtype.kind != "f":
        raise InvalidInputError(f"{name}: expected a floating-point array, got dtype {arr.dtype}", name)
    return np.ascontiguousarray(arr, dtype=np.float32)


__all__ = ["CheckpointError", "HybridMpmError", "InvalidInputError", "SimulationError", "as_f32"]
