"""What every command of the ``hybridmpm`` command line shares: seeds, output folders, JSON, latency summaries."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.errors import InvalidInputError
from hybridmpm.jsonutil import json_safe


def parse_seed(text: str) -> int:
    """argparse type of a seed: an integer in [0, 2^63)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer, got {text!r}") from None
    if not 0 <= v < 2**63:
        raise argparse.ArgumentTypeError(f"must be in [0, 2^63), got {v}")
    return v


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


def latency_ms(seconds: np.ndarray) -> dict[str, float | None]:
    """Per-frame wall time [s] → median/p95/mean in ms (None for no frames)."""
    if len(seconds) == 0:
        return {"median": None, "p95": None, "mean": None}
    ms = np.asarray(seconds) * 1e3
    return {"median": float(np.median(ms)), "p95": float(np.percentile(ms, 95)), "mean": float(ms.mean())}


__all__ = ["latency_ms", "out_dir", "parse_seed", "write_json"]
