"""`hybridmpm generate`: physically sane trajectories, GNS layout for every
scene, byte-identical resume after a kill, the Ray executor in local mode."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hybridmpm.cli import main
from hybridmpm.data import GnsDataset, read_split
from hybridmpm.errors import InvalidInputError
from hybridmpm.scenes import DOMAINS, make_scene, scene_spec
from hybridmpm.scenes.resolution import PAPER_R_P
from hybridmpm.train.datasets import GenerateConfig, generate_dataset, simulate_trajectory, trajectory_seed


def _digest(directory: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(directory.iterdir()) if p.is_file()}


@pytest.mark.parametrize("name", sorted(DOMAINS))
def test_every_scene_generates_train_valid_test(tmp_path, name):
    out = tmp_path / name
    assert main(["generate", name, "--trajectories", "3", "--frames", "4", "--r-t", "2", "--workers", "1", "--out", str(out), "--quiet"]) == 0
    ds = GnsDataset(out)
    assert ds.splits == ("train", "valid", "test")
    meta = ds.metadata
    dim = 3 if name.endswith("3d") else 2
    assert meta["dim"] == dim and meta["sequence_length"] == 2 and meta["dt"] == pytest.approx(5e-3)
    assert len(meta["vel_std"]) == dim and meta["scene"] == name
    for split in ds.splits:
        (traj,) = ds.split(split).values()
        assert traj.positions.shape[0] == 3 and traj.positions.shape[2] == dim
    assert not (out / "parts").exists()
    scenes = json.loads((out / "scenes.json").read_text())
    assert len(scenes) == 3 and {v["split"] for v in scenes.values()} == {"train", "valid", "test"}


@pytest.mark.parametrize(("name", "r_p"), [("water_sand2d", 1.0), ("water_ramps2d", PAPER_R_P), ("sand3d", PAPER_R_P)])
def test_trajectories_are_finite_inside_and_conserve_mass_per_material(name, r_p):
    seed = trajectory_seed(0, 1)
    full = scene_spec(name, seed=seed).build()
    sim = full.make_solver(num_threads=1)
    r = simulate_trajectory(name, seed, frames=60, r_p=r_p, r_t=2)
    x = r["positions"]
    assert x.dtype == np.float32 and x.shape[0] == 31
    assert np.isfinite(x).all()
    dx = 1.0 / full.params.resolved_n_grid()
    assert x.min() >= dx and x.max() <= 1 - dx
    # boundary particles are static; types never change
    fluid = r["particle_type"] != 3
    assert np.array_equal(x[0, ~fluid], x[-1, ~fluid])
    assert fluid.sum() == len(r["masses"]) == len(r["material"])
    # mass per material equals the full-resolution scene's (clusters carry their members' mass)
    for mat in (0, 1):
        assert np.isclose(r["masses"][r["material"] == mat].sum(), sim.masses[full.material == mat].sum(), rtol=1e-5)
    if r_p < 1:
        assert fluid.sum() == pytest.approx(r_p * full.num_particles, abs=2)
    # the fluid moved (gravity acted)
    assert np.abs(x[-1, fluid] - x[0, fluid]).max() > dx


def test_kill_and_resume_gives_the_same_files(tmp_path):
    """SIGKILL a generation once two trajectories are saved, rerun it: the
    dataset is byte-identical to an uninterrupted one with the same seed."""
    args = ["generate", "water2d", "--trajectories", "6", "--frames", "150", "--seed", "3", "--workers", "1", "--quiet"]
    killed = tmp_path / "killed"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "hybridmpm", *args, "--out", str(killed)], env=env)
    deadline = time.time() + 120
    while time.time() < deadline and len(list((killed / "parts").glob("0*.npz"))) < 2 and proc.poll() is None:
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    parts = sorted(p.name for p in (killed / "parts").glob("0*.npz"))
    assert 2 <= len(parts) < 6, "the run was not interrupted halfway"
    assert not (killed / "train.npz").exists()
    mtimes = {p: (killed / "parts" / p).stat().st_mtime_ns for p in parts}
    assert main([*args, "--out", str(killed), "--keep-parts"]) == 0
    # finished trajectories were not redone
    assert all((killed / "parts" / p).stat().st_mtime_ns == t for p, t in mtimes.items())
    whole = tmp_path / "whole"
    assert main([*args, "--out", str(whole), "--keep-parts"]) == 0
    a, b = _digest(killed), _digest(whole)
    assert a == b and {"train.npz", "valid.npz", "test.npz", "metadata.json", "scenes.json"} <= set(a)
    # a second run on a finished dataset does nothing and changes nothing
    assert main([*args, "--out", str(whole)]) == 0
    assert _digest(whole) == b


def test_changed_settings_in_an_existing_directory_are_refused(tmp_path):
    cfg = GenerateConfig("sand2d", trajectories=3, frames=4)
    generate_dataset(cfg, tmp_path, workers=1, progress=False)
    with pytest.raises(InvalidInputError) as e:
        generate_dataset(GenerateConfig("sand2d", trajectories=3, frames=6), tmp_path, workers=1, progress=False)
    assert e.value.field == "frames"
    with pytest.raises(InvalidInputError) as e:
        generate_dataset(GenerateConfig("sand2d", trajectories=3, frames=4, seed=1), tmp_path, workers=1, progress=False)
    assert e.value.field == "seed"


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"trajectories": 2}, "trajectories"),
        ({"r_p": 0.0}, "r_p"),
        ({"r_t": 0}, "r_t"),
        ({"frames": 1}, "frames"),
        ({"split": (0.5, 0.5, 0.5)}, "split"),
        ({"scene": "lava2d"}, "scene"),
    ],
)
def test_bad_settings_name_the_field(tmp_path, kwargs, field):
    cfg = GenerateConfig(**{"scene": "water2d", "trajectories": 3, "frames": 4, **kwargs})
    with pytest.raises(InvalidInputError) as e:
        generate_dataset(cfg, tmp_path, workers=1, progress=False)
    assert e.value.field == field


def test_statistics_in_metadata_match_the_training_split(tmp_path):
    generate_dataset(GenerateConfig("water_ramps2d", trajectories=4, frames=12, r_t=3), tmp_path, workers=2, progress=False)
    meta = json.loads((tmp_path / "metadata.json").read_text())
    train = read_split(tmp_path / "train.npz")
    vel, acc = [], []
    for t in train.values():
        x = t.positions.astype(np.float64)[:, t.particle_type != 3]
        v = np.diff(x, axis=0)
        vel.append(v.reshape(-1, 2))
        acc.append(np.diff(v, axis=0).reshape(-1, 2))
    vel_a, acc_a = np.concatenate(vel), np.concatenate(acc)
    assert np.allclose(meta["vel_mean"], vel_a.mean(0), rtol=1e-6, atol=1e-12)
    assert np.allclose(meta["vel_std"], vel_a.std(0), rtol=1e-6)
    assert np.allclose(meta["acc_std"], acc_a.std(0), rtol=1e-6)
    assert meta["dt"] == pytest.approx(3 * 2.5e-3) and meta["sequence_length"] == 4
    # the stored trajectory is the MPM rollout of the recorded initial condition
    scenes = json.loads((tmp_path / "scenes.json").read_text())
    tid, info = next(iter(sorted(scenes.items())))
    scene = make_scene("water_ramps2d", seed=info["seed"], frames=12)
    assert scene.spec is not None and scene.spec.to_dict() == info["spec"]
    sim = scene.make_solver()
    for _ in range(3):
        sim.step_frame()
    assert np.array_equal(train[tid].positions[1, : scene.num_particles], sim.positions)


def test_ray_executor_in_local_mode_matches_the_process_pool(tmp_path):
    """The Ray executor (a local Ray instance, 2 CPUs) produces the same bytes
    as the process pool."""
    pytest.importorskip("ray", reason="Ray is in the 'test' and 'cluster' extras; without it the executor cannot run")
    cfg = GenerateConfig("water_sand2d", trajectories=3, frames=6, seed=5, r_p=PAPER_R_P)
    generate_dataset(cfg, tmp_path / "ray", workers=2, executor="ray", progress=False)
    generate_dataset(cfg, tmp_path / "pool", workers=2, executor="process", progress=False)
    assert _digest(tmp_path / "ray") == _digest(tmp_path / "pool")


def test_inspect_reads_a_dataset_written_by_another_tool(tmp_path, capsys):
    """A GNS dataset made elsewhere (np.savez_compressed of object arrays, the
    public metadata fields only) is read and summarised."""
    rng = np.random.default_rng(0)
    for split, n in (("train", 2), ("valid", 1), ("test", 1)):
        items = {}
        for i in range(n):
            item = np.empty(2, dtype=object)
            item[0] = rng.uniform(0.1, 0.9, (7, 30, 2)).astype(np.float32)
            item[1] = np.r_[np.full(25, 5), np.full(5, 3)].astype(np.int64)
            items[f"simulation_trajectory_{i}"] = item
        np.savez_compressed(tmp_path / f"{split}.npz", **items)
    meta = {
        "bounds": [[0.1, 0.9], [0.1, 0.9]], "sequence_length": 6, "default_connectivity_radius": 0.015, "dim": 2, "dt": 0.0025,
        "vel_mean": [0.0, 0.0], "vel_std": [1e-3, 1e-3], "acc_mean": [0.0, 0.0], "acc_std": [1e-4, 1e-4],
    }  # fmt: skip
    (tmp_path / "metadata.json").write_text(json.dumps(meta))
    assert main(["inspect", str(tmp_path)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["splits"]["train"]["trajectories"] == 2 and info["splits"]["test"]["frames"] == [7]
    assert info["splits"]["valid"]["particle_types"] == [3, 5] and info["metadata"]["dt"] == 0.0025
    # a broken dataset is a clear error, not a traceback
    (tmp_path / "metadata.json").write_text(json.dumps({k: v for k, v in meta.items() if k != "dt"}))
    assert main(["inspect", str(tmp_path)]) == 2
    assert "dt" in capsys.readouterr().err
