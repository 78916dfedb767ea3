"""`hybridmpm simulate` writes the documented files."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from hybridmpm.cli import main
from hybridmpm.scenes import dam_break2d


def test_simulate_writes_trajectory_summary_and_render(tmp_path):
    out = tmp_path / "db"
    assert main(["simulate", "dam_break2d", "--solver", "mpm", "--frames", "6", "--out", str(out), "--quiet"]) == 0
    traj = np.load(out / "trajectory.npz")
    scene = dam_break2d()
    assert traj["positions"].shape == (7, scene.num_particles, 2)
    assert traj["positions"].dtype == np.float32
    assert np.array_equal(traj["positions"][0], scene.positions)
    assert (traj["particle_type"] == 5).all()
    assert float(traj["dt_frame"]) == 2.5e-3
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 6 and summary["particles"] == scene.num_particles
    assert summary["substeps_per_frame"]["min"] >= 16
    assert summary["wall_ms_per_frame"]["p95"] >= summary["wall_ms_per_frame"]["median"] > 0
    gif = (out / "render.gif").read_bytes()
    assert gif[:6] in (b"GIF87a", b"GIF89a")


def test_unknown_scene_is_a_clear_error(tmp_path):
    r = subprocess.run([sys.executable, "-m", "hybridmpm", "simulate", "nope", "--out", str(tmp_path)], capture_output=True, text=True)
    assert r.returncode == 2 and "nope" in r.stderr
