"""What the architecture tests (tests/test_architecture*.py) share: where the
repository, the package, its service and the service's page live."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "python" / "hybridmpm"
SERVICE = PACKAGE / "service"
STATIC = SERVICE / "static"
