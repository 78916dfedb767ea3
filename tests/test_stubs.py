"""The `_core.pyi` stubs agree with the compiled module (mypy.stubtest)."""

from __future__ import annotations

import subprocess
import sys


def test_stubtest():
    r = subprocess.run(
        [sys.executable, "-m", "mypy.stubtest", "hybridmpm._core"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stdout + r.stderr
