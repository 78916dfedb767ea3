"""The layout keeps its promises (docs/architecture.md): one frame loop, one
definition of each code and default."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _sources(*dirs: str) -> list[Path]:
    return [p for d in dirs for p in (ROOT / d).rglob("*.py")]


def test_frames_are_advanced_only_inside_hybridmpm_sim():
    # MpmSolver.step_frame is called by the simulators; everything else goes through rollout
    sim = ROOT / "python" / "hybridmpm" / "sim"
    offenders = []
    for p in _sources("python", "benchmarks", "docs"):
        for i, line in enumerate(p.read_text().splitlines(), 1):
            if "step_frame(" in line and sim not in p.parents and not line.lstrip().startswith(("def step_frame", "return self._core.step_frame")):
                offenders.append(f"{p.relative_to(ROOT)}:{i}: {line.strip()}")
    assert not offenders, "\n".join(offenders)


def test_codes_and_defaults_are_defined_once():
    # the numbers of hybridmpm.conventions are not restated as module constants elsewhere
    pattern = re.compile(
        r"^(WATER|SAND|KINEMATIC|GNS_(?:KINEMATIC|WATER|SAND|TYPE\w*)|MATERIAL_\w+|CONNECTIVITY_RADIUS|T_IN|T_CTR|R_C|DELTA|SPLITS|DT_FRAME|DEFAULT_RADIUS|DEFAULT_CONNECTIVITY_RADIUS|DEFAULT_N_GRID)\s*(:[^=]*)?=\s*[\d(\[{\"']"
    )
    offenders = []
    for p in _sources("python"):
        if p.name == "conventions.py":
            continue
        for i, line in enumerate(p.read_text().splitlines(), 1):
            if pattern.match(line):
                offenders.append(f"{p.relative_to(ROOT)}:{i}: {line.strip()}")
    assert not offenders, "\n".join(offenders)


def test_the_taichi_peer_is_not_in_the_package():
    assert not (ROOT / "python" / "hybridmpm" / "bench" / "taichi_peer.py").exists()
    for p in _sources("python"):
        assert "import taichi" not in p.read_text(), p
