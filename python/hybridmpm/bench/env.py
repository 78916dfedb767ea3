"""The machine and versions recorded with every benchmark result."""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path
from typing import Any


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

    import hybridmpm

    return {
        "machine": f"{platform.machine()} {cpu_model()}",
        "cores": os.cpu_count() or 0,
        "hybridmpm": hybridmpm.__version__,
        "numpy": numpy.__version__,
        "onnxruntime": onnxruntime.__version__,
        "python": platform.python_version(),
        "commit": git_commit(),
    }


__all__ = ["cpu_model", "environment", "git_commit"]
