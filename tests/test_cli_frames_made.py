"""A command that runs a rollout for a requested frame count fails (exit status 2, one line on
stderr saying how many frames of how many were made and why) when the rollout broke off early,
and keeps the files of the frames it made."""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np

#: Still water dropped in a strong gravity with few substeps allowed a frame: the first frames
#: need 8 substeps (the wave speed alone), but the water falls 1 m/s faster every frame and from
#: the fourth frame on the CFL condition needs 10 > max_substeps = 9, so MPM cannot finish it.
#: Nothing in the scene is refused when it is built (no initial velocity, a legal substep cap):
#: it fails while it runs.
FALLING = """
name = "falling"
dim = 2
n_grid = 64
max_substeps = 9
gravity = [0.0, -400.0]
[[blocks]]
material = "water"
lo = [0.3, 0.5]
hi = [0.5, 0.7]
"""
#: The frames it makes before MPM gives up (see above).
FALLING_MADE = 3


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hybridmpm", *args], capture_output=True, text=True, timeout=120)


def _error_line(r: subprocess.CompletedProcess[str]) -> str:
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr  # --quiet: no progress bar, only the error
    return lines[0]


def test_simulate_fails_when_frames_asked_are_not_made_and_keeps_them(tmp_path):
    scene = tmp_path / "falling.toml"
    scene.write_text(FALLING)
    out = tmp_path / "out"
    r = _cli("simulate", str(scene), "--solver", "mpm", "--frames", "8", "--threads", "1", "--out", str(out), "--quiet", "--no-render")
    assert r.returncode == 2, (r.returncode, r.stderr)
    line = _error_line(r)
    assert line.startswith("hybridmpm: error: simulate: ")
    assert f"made {FALLING_MADE} of 8 frames" in line
    assert "broke off: mpm" in line and "max_substeps = 9" in line  # the rollout's failure and its text
    assert str(out) in line
    # what was made is kept: the trajectory of the frames made and the summary that says so
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == FALLING_MADE and summary["frames_asked"] == 8 and summary["failure"] == "mpm"
    traj = np.load(out / "trajectory.npz")
    assert traj["positions"].shape[0] == FALLING_MADE + 1


def test_simulate_that_makes_every_frame_exits_0(tmp_path):
    scene = tmp_path / "falling.toml"
    scene.write_text(FALLING)
    out = tmp_path / "out"
    r = _cli("simulate", str(scene), "--solver", "mpm", "--frames", str(FALLING_MADE), "--threads", "1", "--out", str(out), "--quiet", "--no-render")
    assert r.returncode == 0, r.stderr
    assert r.stderr.strip() == ""
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == FALLING_MADE and summary["failure"] is None


def test_control_fails_when_frames_asked_are_not_made(tmp_path):
    scene = tmp_path / "falling.toml"
    scene.write_text(FALLING)
    sketch = tmp_path / "arrow.json"
    sketch.write_text(json.dumps({"kind": "arrow", "points": [[0.3, 0.5], [0.6, 0.5]]}))
    common = ("--sketch", str(sketch), "--method", "constant", "--solver", "mpm", "--threads", "1", "--quiet", "--no-render")
    # the controlled frames break off: the files hold the frames made
    out = tmp_path / "during"
    r = _cli("control", str(scene), *common, "--from-frame", "0", "--frames", "8", "--out", str(out))
    assert r.returncode == 2, (r.returncode, r.stderr)
    line = _error_line(r)
    assert re.search(r"control: made \d of 8 frames; broke off: mpm", line), line
    made = int(re.search(r"made (\d) of", line).group(1))  # type: ignore[union-attr]
    assert made < 8 and json.loads((out / "summary.json").read_text())["frames"] == made
    assert np.load(out / "trajectory.npz")["positions"].shape[0] == made + 1
    # the frames before the sketch break off: the sketch never applies, nothing is written
    out = tmp_path / "before"
    r = _cli("control", str(scene), *common, "--from-frame", "8", "--frames", "8", "--out", str(out))
    assert r.returncode == 2, (r.returncode, r.stderr)
    assert f"control: before the sketch: made {FALLING_MADE} of 8 frames; broke off: mpm" in _error_line(r)
    assert not (out / "trajectory.npz").exists()
