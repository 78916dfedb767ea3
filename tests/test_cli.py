"""`hybridmpm simulate` writes the documented files."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from hybridmpm.cli import main
from hybridmpm.models import shipped_default
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


def test_simulate_a_scene_with_obstacles_writes_boundary_particles_and_renders(tmp_path):
    from hybridmpm.scenes import make_scene

    out = tmp_path / "ramps"
    assert main(["simulate", "water_ramps2d", "--seed", "3", "--solver", "mpm", "--frames", "3", "--out", str(out), "--quiet"]) == 0
    scene = make_scene("water_ramps2d", seed=3)
    traj = np.load(out / "trajectory.npz")
    n, b = scene.num_particles, scene.num_boundary
    assert b > 0 and traj["positions"].shape == (4, n + b, 2)
    assert (traj["particle_type"][n:] == 3).all()
    assert np.array_equal(traj["positions"][3, n:], scene.boundary_positions)  # static
    assert (out / "render.gif").read_bytes()[:3] == b"GIF"
    # a downsampled run: fewer solver particles, the same boundary treatment
    low = tmp_path / "low"
    assert (
        main(["simulate", "water_ramps2d", "--seed", "3", "--solver", "mpm", "--frames", "2", "--r-p", "0.5", "--out", str(low), "--quiet", "--no-render"]) == 0
    )
    summary = json.loads((low / "summary.json").read_text())
    assert summary["particles"] == round(0.5 * n) and summary["r_p"] == 0.5


def test_control_command_writes_its_outputs(tmp_path):
    sketch = tmp_path / "arrow.json"
    sketch.write_text(json.dumps({"kind": "arrow", "points": [[0.3, 0.2], [0.5, 0.3]]}))
    out = tmp_path / "ctl"
    assert (
        main(
            [
                "control",
                "water2d",
                "--sketch",
                str(sketch),
                "--method",
                "constant",
                "--frames",
                "20",
                "--from-frame",
                "8",
                "--out",
                str(out),
                "--quiet",
                "--threads",
                "1",
            ]
        )
        == 0
    )
    s = json.loads((out / "summary.json").read_text())
    assert s["frames"] == 20 and s["method"] == "constant" and s["cosine"] > 0.5 and s["solver"] == "default"
    assert (out / "render.gif").read_bytes()[:3] == b"GIF" and (out / "sketch.png").read_bytes()[:4] == b"\x89PNG"
    traj = np.load(out / "trajectory.npz")
    r_t = shipped_default("water2d")["config"]["r_t"]  # the scene's default configuration runs without --solver
    assert traj["positions"].shape[0] == 20 // r_t + 1  # 20 frames at the default's r_t, plus the start
    (tmp_path / "bad.json").write_text('{"kind": "spiral", "points": [[0, 0], [1, 1]]}')
    assert main(["control", "water2d", "--sketch", str(tmp_path / "bad.json"), "--out", str(out), "--quiet"]) == 2
