"""The machine and versions recorded with every benchmark result."""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path
from typing import Any

from hybridmpm import _core


def cpu_model() -> str:
    """The CPU's model name (with family/model/stepping on Linux)."""
    info: dict[str, str] = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if ":" in line:
                    k, val = line.split(":", 1)
                    info.setdefault(k.strip(), val.strip())
    except OSError:
        pass
    name = info.get("model name") or platform.processor() or "unknown"
    if "cpu family" in info and "model" in info:
        name += f" (family {info['cpu family']}, model {info['model']}, stepping {info.get('stepping', '?')})"
    return name


def git_commit() -> str:
    """The repository's HEAD commit, with ``-dirty`` if the code (tracked files
    under ``python/`` or ``rust/``) differs from it; recorded results being
    rewritten do not count (``unknown`` outside a git checkout)."""
    try:
        here = Path(__file__).resolve().parent
        out = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=here, capture_output=True, text=True, timeout=10)
        head = out.stdout.strip()
        if not head:
            return "unknown"
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no", "--", ":/python", ":/rust"], cwd=here, capture_output=True, text=True, timeout=10
        )
        return head + ("-dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def environment() -> dict[str, Any]:
    """Machine and versions recorded with every result row."""
    import numpy
    import onnxruntime

    return {
        "machine": f"{platform.machine()} {cpu_model()}",
        "cores": os.cpu_count() or 0,
        "hybridmpm": _core.__version__,
        "numpy": numpy.__version__,
        "onnxruntime": onnxruntime.__version__,
        "python": platform.python_version(),
        "commit": git_commit(),
    }


def cpu_times() -> tuple[int, int] | None:
    """``(steal, total)`` jiffies of all CPUs since boot from ``/proc/stat``
    (Linux; None elsewhere). Steal is time the hypervisor gave this virtual
    machine's CPUs to someone else: a timing taken while it grows is not quiet."""
    try:
        with open("/proc/stat") as f:
            fields = f.readline().split()
    except OSError:
        return None
    if not fields or fields[0] != "cpu" or len(fields) < 9:
        return None
    values = [int(v) for v in fields[1:9]]  # user nice system idle iowait irq softirq steal
    return values[7], sum(values)


def steal_fraction(before: tuple[int, int] | None, after: tuple[int, int] | None) -> float | None:
    """Share of CPU time stolen between two :func:`cpu_times` readings (None if unknown)."""
    if before is None or after is None or after[1] <= before[1]:
        return None
    return (after[0] - before[0]) / (after[1] - before[1])


__all__ = ["cpu_model", "cpu_times", "environment", "git_commit", "steal_fraction"]
