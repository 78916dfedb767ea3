"""Memory budget: every allocation that scales with an input is estimated
first and refused beyond it, with an error naming the input and the size it
would need (docs/limits.md).

The budget defaults to half of the machine's physical memory; set
``HYBRIDMPM_MEMORY_BUDGET`` (bytes, or with a suffix: ``512M``, ``8G``) or
call :func:`set_memory_budget` to change it. It bounds one allocation (one
array, one grid, one edge list), not the process: a service running several
sessions should set it to its per-session share.
"""

from __future__ import annotations

import numbers
import os
import re

from hybridmpm.errors import InvalidInputError

#: Environment variable overriding the default budget.
ENV_VAR = "HYBRIDMPM_MEMORY_BUDGET"
#: Fraction of physical memory the default budget allows.
DEFAULT_FRACTION = 0.5

#: Largest frame number a simulator state may hold (a restored ``step_index ·
#: r_t``, and every counter of steps): int64 holds it and the simulated time
#: ``frame · dt_frame`` stays exact in float64. Larger values are refused.
MAX_FRAME_INDEX = 2**53

#: Seeds are integers in [0, MAX_SEED) = [0, 2^63): what int64 and numpy's generators hold. A seed
#: derived from another (a first seed plus a count, a trajectory's index) must stay in range too; a
#: library whose seeds are narrower (scikit-learn's k-means: [0, 2^32)) gets one derived from it
#: (:func:`hybridmpm.scenes.resolution.kmeans_seed`).
MAX_SEED = 2**63

_override: int | None = None
#: The largest float32 magnitude and the smallest normal one: the solver computes in float32, where a number past
#: the first is infinite and one under the second loses its digits or becomes 0.
F32_MAX = 3.4028234663852886e38
F32_TINY = 1.1754943508222875e-38


def check_float32(field: str, value: float) -> float:
    """``value`` (the user's number for ``field``, finite) if float32 holds it as a normal number or 0; else
    :class:`InvalidInputError` naming ``field`` with the value given (``density = 1e-300`` is 0 in float32, ``E =
    1e39`` infinite)."""
    if abs(value) > F32_MAX:
        raise InvalidInputError(f"{field}: {value!r} is past float32's largest number ({F32_MAX:.4g}), the solver's precision", field)
    if value != 0 and abs(value) < F32_TINY:
        raise InvalidInputError(f"{field}: {value!r} is below float32's smallest normal number ({F32_TINY:.4g}), the solver's precision", field)
    return value


_UNITS = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def parse_size(text: str | int, field: str = ENV_VAR) -> int:
    """``"8G"``, ``"512M"``, ``"1.5G"``, ``"1000000"`` or an int → bytes (> 0).
    Raises :class:`InvalidInputError` naming ``field``."""
    if isinstance(text, int) and not isinstance(text, bool):
        value = float(text)
    else:
        m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+(?:[eE][+-]?[0-9]+)?)\s*([KMGT]?)(?:i?B)?\s*", str(text), re.IGNORECASE)
        if not m:
            raise InvalidInputError(f"{field}: expected a size in bytes such as 8G or 512M, got {text!r}", field)
        value = float(m.group(1)) * _UNITS[m.group(2).upper()]
    if not value >= 1:
        raise InvalidInputError(f"{field}: must be at least 1 byte, got {text!r}", field)
    return int(value)


def physical_memory() -> int:
    """Physical memory of the machine [bytes] (16 GiB if it cannot be read)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 16 * 2**30


def memory_budget() -> int:
    """The budget of one allocation [bytes]: :func:`set_memory_budget`'s value,
    else ``HYBRIDMPM_MEMORY_BUDGET``, else half the physical memory."""
    if _override is not None:
        return _override
    env = os.environ.get(ENV_VAR)
    if env:
        return parse_size(env)
    return int(DEFAULT_FRACTION * physical_memory())


def set_memory_budget(size: str | int | None) -> None:
    """Set the budget for this process (None: back to the default)."""
    global _override
    _override = None if size is None else parse_size(size, "memory_budget")


def human(nbytes: float) -> str:
    """``nbytes`` as a short human-readable size (``3.2 GiB``)."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(nbytes) < 1024 or unit == "PiB":
            return f"{nbytes:.0f} {unit}" if unit == "B" else f"{nbytes:.1f} {unit}"
        nbytes /= 1024
    return f"{nbytes:.1f} PiB"  # pragma: no cover


def check_seed(value: object, field: str = "seed") -> int:
    """``value`` as a seed: an integer (not a bool) in [0, :data:`MAX_SEED`) = [0, 2^63).
    Raises :class:`InvalidInputError` naming ``field`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or not 0 <= int(value) < MAX_SEED:
        raise InvalidInputError(f"{field}: must be an integer in [0, 2^63), got {value!r}", field)
    return int(value)


def check_allocation(field: str, nbytes: float, what: str) -> None:
    """Refuse an allocation of ``nbytes`` for ``what`` beyond the budget:
    :class:`InvalidInputError` naming ``field`` and the size needed."""
    budget = memory_budget()
    if not nbytes <= budget:
        raise InvalidInputError(
            f"{field}: {what} would need {human(nbytes)}, over the memory budget of {human(budget)} (set {ENV_VAR} to change it)",
            field,
        )


__all__ = [
    "DEFAULT_FRACTION",
    "ENV_VAR",
    "MAX_SEED",
    "check_allocation",
    "check_seed",
    "human",
    "memory_budget",
    "parse_size",
    "physical_memory",
    "set_memory_budget",
]
