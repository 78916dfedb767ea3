"""What every command of the ``hybridmpm`` command line shares: seeds, output folders, JSON, latency summaries."""

from __future__ import annotations

import argparse
import json
import os
import stat
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError, SimulationError
from hybridmpm.files import FILE_KINDS
from hybridmpm.jsonutil import json_safe
from hybridmpm.limits import MAX_SEED


def parse_seed(text: str) -> int:
    """argparse type of a seed: an integer in [0, 2^63) (:data:`hybridmpm.limits.MAX_SEED`)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None
    if not 0 <= v < MAX_SEED:
        raise argparse.ArgumentTypeError(f"must be in [0, 2^63), got {v}")
    return v


def seed_range(first: int, count: int, flag: str, count_flag: str, max_count: int) -> list[int]:
    """The seeds ``first``, ``first + 1``, … (``count`` of them) that ``flag`` and ``count_flag`` ask
    for, checked before any work: ``count`` in [1, ``max_count``] and the last one below 2^63 (every
    derived seed in range). Raises :class:`InvalidInputError` naming the flag's field otherwise."""
    count_field, field = count_flag.lstrip("-").replace("-", "_"), flag.lstrip("-").replace("-", "_")
    if isinstance(count, bool) or not isinstance(count, int) or not 1 <= count <= max_count:
        raise InvalidInputError(f"{count_field}: {count_flag} must be an integer in [1, {max_count}], got {count!r}", count_field)
    if not 0 <= first or first + count > MAX_SEED:
        raise InvalidInputError(
            f"{field}: the seeds {flag} {first} … {first + count - 1} ({count_flag} {count}) must lie in [0, 2^63): at most {flag} {MAX_SEED - count}",
            field,
        )
    return [first + i for i in range(count)]


def out_file(path: str | Path, field: str = "out", *, replace: bool = False) -> Path:
    """Check, before any work, that the file ``path`` can be written when the work is done: its
    folder is created (:func:`out_dir`: parents too, and writable) and ``path`` is not a directory,
    a device such as ``/dev/full``, a FIFO, nor (unless ``replace``) an existing file. Raises
    :class:`InvalidInputError` naming ``field`` otherwise. Nothing is written to ``path`` itself."""
    out = Path(path)
    try:
        st = out.stat()
    except FileNotFoundError:
        st = None
    except OSError as e:
        raise InvalidInputError(f"{field}: cannot write to {out} ({e.strerror or e})", field) from e
    if st is not None and not stat.S_ISREG(st.st_mode):
        raise InvalidInputError(f"{field}: {out} is {FILE_KINDS.get(stat.S_IFMT(st.st_mode), 'not a regular file')}, not a file it can write", field)
    if st is not None and not replace:
        raise InvalidInputError(f"{field}: {out} exists; remove it or choose another {'--' + field.replace('_', '-')}", field)
    out_dir(out.parent if str(out.parent) else ".", field)
    return out


def out_dir(path: str | Path, field: str = "out") -> Path:
    """Create output directory ``path`` (parents too) and check that it can be
    written, before any work: raises :class:`InvalidInputError` naming
    ``field`` otherwise."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise InvalidInputError(f"{field}: {out} exists and is not a directory", field)
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / f".hybridmpm-write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise InvalidInputError(f"{field}: cannot write to {out} ({e.strerror or e})", field) from e
    return out


def write_json(path: Path, obj: Any) -> None:
    """Write strict JSON atomically (a temporary file beside it, then a rename)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(json_safe(obj), indent=2, allow_nan=False))
    tmp.replace(path)


def check_frames_made(command: str, made: int, asked: int, failure: str | None, detail: str | None, kept: str | None = None) -> None:
    """Raise :class:`~hybridmpm.errors.SimulationError` (the command line's one line on stderr, exit
    status 2) when a rollout made fewer frames (``made``) than were asked for (``asked``): it says how many
    of how many, why it broke off (the rollout's ``failure`` and ``failure_detail``, on one line) and
    ``kept``, where what was made is saved (None: nothing is). Called once the command has written its files."""
    if made >= asked:
        return
    why = failure or "unknown"
    if detail:
        why += f" ({' '.join(str(detail).split())})"
    where = f"; the {made} frames made are saved in {kept}" if kept else ""
    raise SimulationError(f"{command}: made {made} of {asked} frames; broke off: {why}{where}")


def latency_ms(seconds: np.ndarray) -> dict[str, float | None]:
    """Per-frame wall time [s] → median/p95/mean in ms (None for no frames)."""
    if len(seconds) == 0:
        return {"median": None, "p95": None, "mean": None}
    ms = np.asarray(seconds) * 1e3
    return {"median": float(np.median(ms)), "p95": float(np.percentile(ms, 95)), "mean": float(ms.mean())}


__all__ = ["check_frames_made", "latency_ms", "out_dir", "out_file", "parse_seed", "seed_range", "write_json"]
