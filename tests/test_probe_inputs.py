"""Bad input a hostile probe found, each refused at once with one line naming
the field or flag (docs/limits.md):

* a model file that never ends (``/dev/zero``, a link to it, a FIFO) or one
  over ``MAX_MODEL_BYTES`` is refused without blocking and before it is read;
* ``evaluate`` refuses a ratio of frame intervals it cannot pair in int64,
  and sizes its per-frame work and output from the files' headers against
  the memory budget before comparing a frame;
* a scene file named like a registered scene runs as given (a default
  belongs to a registered scene, not to a name);
* seeds, and the seeds derived from them, are checked to lie in [0, 2^63)
  before any work (k-means gets one derived from the seed);
* a configuration flag given with the default solver is refused whatever
  its value (``--r-p 1.0`` included);
* a corrupt ``models/defaults.json``, and ``tune``'s ``--out`` and
  ``--work``, end in one line naming the file or the flag.

The CLI cases that could block or read without end on a broken build run in
a subprocess with a timeout and a 4 GiB address-space limit."""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from hybridmpm.cli import main
from hybridmpm.conventions import R_C
from hybridmpm.errors import InvalidInputError
from hybridmpm.files import MAX_MODEL_BYTES
from hybridmpm.metrics import align_frames
from hybridmpm.neural.base import open_model, read_header


def _limit_memory() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))


def _run(argv: list[str], tmp_path: Path, timeout: float = 30, **env: str) -> tuple[int, str, float]:
    """``hybridmpm ARGV`` in a subprocess (4 GiB of address space, ``timeout`` s): (exit code, stderr, seconds)."""
    t0 = time.perf_counter()
    r = subprocess.run(
        [sys.executable, "-m", "hybridmpm", *argv],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=timeout,
        preexec_fn=_limit_memory,
        env={**os.environ, **env},
    )
    return r.returncode, r.stderr.strip(), time.perf_counter() - t0


def _cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """``hybridmpm ARGV`` in this process (argparse's exit counts as its code): (exit code, stderr)."""
    try:
        code = main(argv)
    except SystemExit as e:
        code = int(e.code or 0)
    return code, capsys.readouterr().err.strip()


def _refused(code: int, err: str, *names: str) -> None:
    """A refusal: exit 2, one line (argparse's usage aside), naming each of ``names``, no traceback."""
    assert code == 2, (code, err)
    assert "Traceback" not in err, err
    last = err.splitlines()[-1]
    assert last.startswith(("hybridmpm: error:", "hybridmpm ")), err
    for name in names:
        assert name in last, (name, err)


def test_a_model_file_that_never_ends_is_refused_without_reading_it(tmp_path):
    zero_link = tmp_path / "zero.onnx"
    zero_link.symlink_to("/dev/zero")
    fifo = tmp_path / "fifo.onnx"
    os.mkfifo(fifo)
    huge = tmp_path / "huge.onnx"
    with open(huge, "wb") as f:  # sparse: one byte past the bound, no disk
        f.truncate(MAX_MODEL_BYTES + 1)
    short = ["--frames", "2", "--warmup", "0", "--seeds", "1", "--no-variants", "--r-c", "0.5", "--error-tols", "", "--quiet"]
    for argv, names in (
        (["simulate", "water2d", "--solver", "neural", "--model", "/dev/zero", "--frames", "4"], ("model", "/dev/zero", "character device")),
        (["simulate", "water2d", "--solver", "hybrid", "--model", str(zero_link), "--frames", "4"], ("model", "character device")),
        (["simulate", "water2d", "--solver", "neural", "--model", str(fifo), "--frames", "4"], ("model", "FIFO")),
        (["simulate", "water2d", "--solver", "neural", "--model", str(huge), "--frames", "4"], ("model", "more than")),
        (["bench", "water2d", "--model", str(fifo), "--out", "b", *short], ("model", "FIFO")),
        (["bench", "water2d", "--extra-model", "/dev/zero", "--out", "b", *short], ("extra_models", "character device")),
        (["tune", "water2d", "--error-budget", "1", "--model", str(zero_link), "--out", "t.json", "--work", "w", *short], ("model",)),
    ):
        code, err, seconds = _run(argv, tmp_path)
        _refused(code, err, *names)
        assert seconds < 10, (argv, seconds)
    # in this process too (once the CLI, in a subprocess, showed that nothing blocks or reads without end)
    for path, what in (("/dev/zero", "character device"), (zero_link, "character device"), (huge, "more than")):
        for call in (read_header, open_model):
            with pytest.raises(InvalidInputError) as e:
                call(path)
            assert e.value.field == "model" and what in str(e.value), str(e.value)


def _trajectory(path: Path, frames: int, dt_frame: float) -> Path:
    np.savez_compressed(path, positions=np.full((frames, 1, 2), 0.5, np.float32), particle_type=np.full(1, 5), dt_frame=np.float64(dt_frame))
    return path


def test_evaluate_refuses_frame_intervals_whose_ratio_overflows(tmp_path, capsys):
    ref = _trajectory(tmp_path / "ref.npz", 4, 2.5e-3)
    for dt in (1e-30, 1e300, 5e-324):
        with pytest.raises(InvalidInputError) as e:
            align_frames(dt, 4, 2.5e-3, 4)
        assert e.value.field == "pred_dt", str(e.value)
        with pytest.raises(InvalidInputError):
            align_frames(2.5e-3, 4, dt, 4)
        pred = _trajectory(tmp_path / "pred.npz", 4, dt)
        code, err = _cli(["evaluate", str(pred), str(ref), "--out", str(tmp_path / "m.json"), "--quiet"], capsys)
        _refused(code, err, "pred_dt")
        assert not (tmp_path / "m.json").exists()
    # a large ratio that holds still pairs: frame 0 (and the ones both store)
    assert [a.tolist() for a in align_frames(2.5e-3 * 2**40, 3, 2.5e-3, 4)[:2]] == [[0], [0]]


def test_evaluate_sizes_its_per_frame_work_from_the_headers_before_comparing(tmp_path):
    # a million frames of one particle (a few kB deflated) under 64 MiB; five million under 256 MiB (they load, their comparison does not fit)
    for frames, budget in ((1_000_000, "64M"), (5_000_000, "256M")):
        a, b = _trajectory(tmp_path / f"a{frames}.npz", frames, 2.5e-3), _trajectory(tmp_path / f"b{frames}.npz", frames, 2.5e-3)
        assert a.stat().st_size < 200_000
        code, err, seconds = _run(["evaluate", str(a), str(b), "--out", "m.json"], tmp_path, HYBRIDMPM_MEMORY_BUDGET=budget)
        _refused(code, err, "frames", f"comparing {frames} frames", "over the memory budget")
        assert seconds < 5, seconds
        assert not (tmp_path / "m.json").exists()


def _scene_file(path: Path, name: str) -> Path:
    """A 2D scene file of its own: a 32² grid and one block of 4 × 6 lattice points (24 particles)."""
    block = {"material": "water", "lo": [0.3, 0.3], "hi": [0.3 + 4 / 64, 0.3 + 6 / 64]}
    path.write_text(json.dumps({"name": name, "dim": 2, "n_grid": 32, "frames": 2, "blocks": [block]}))
    return path


def test_a_scene_file_named_like_a_registered_scene_runs_as_given(tmp_path, capsys):
    from hybridmpm.scenes import make_scene, registered_name
    from hybridmpm.sim import default_settings, make_simulator

    assert registered_name(make_scene("water2d")) == "water2d" and registered_name("water2d") == "water2d"
    for name in ("water2d", "water3d"):
        path = _scene_file(tmp_path / f"{name}.json", name)
        scene = make_scene(str(path))
        assert scene.name == name and registered_name(scene) is None
        assert default_settings(scene) == {"solver": "mpm"}
        sim = make_simulator(scene, "default", threads=1)
        assert sim.scene.num_particles == 24 and sim.scene.params.resolved_n_grid() == 32
        out = tmp_path / f"out_{name}"
        code, err = _cli(["simulate", str(path), "--frames", "2", "--threads", "1", "--out", str(out), "--no-render", "--quiet"], capsys)
        assert code == 0, err
        summary = json.loads((out / "summary.json").read_text())
        got = (summary["particles"], summary["n_grid"], summary["solver"], summary["configuration"], summary["default"])
        assert got == (24, 32, "mpm", "default", None), summary


def test_seeds_out_of_range_are_refused_before_any_work(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # whatever a broken build writes stays here
    from hybridmpm.scenes import scene_spec
    from hybridmpm.scenes.resolution import KMEANS_SEEDS, cluster_particles, kmeans_seed
    from hybridmpm.sim import make_simulator

    short = ["--frames", "2", "--warmup", "0", "--no-variants", "--quiet"]
    t0 = time.perf_counter()
    for argv, names in (
        (["bench", "water2d", "--first-seed", "-5", "--out", str(tmp_path / "b")], ("--first-seed",)),
        (["bench", "water2d", "--first-seed", str(2**63 - 1), "--out", str(tmp_path / "b")], ("first_seed", "--first-seed", "2^63")),
        (["bench", "water2d", "--first-seed", str(2**63 - 2), "--seeds", "3", "--out", str(tmp_path / "b")], ("first_seed",)),
        (["bench", "water2d", "--seeds", str(10**12), "--out", str(tmp_path / "b")], ("seeds", "--seeds")),
        (["tune", "water2d", "--error-budget", "1", "--seeds", "0", "--out", str(tmp_path / "t.json"), "--work", "w"], ("seeds",)),
        (["simulate", "water2d", "--seed", "-1", "--out", str(tmp_path / "s")], ("--seed",)),
        (["simulate", "water2d", "--seed", str(2**63), "--out", str(tmp_path / "s")], ("--seed",)),
        (["export", str(tmp_path / "none.npz"), "--seed", "-1", "--out", str(tmp_path / "e")], ("--seed",)),
        (["generate", "water2d", "--seed", "-1", "--out", str(tmp_path / "g")], ("--seed",)),
    ):
        code, err = _cli(argv + (short if argv[0] in ("bench", "tune") else []), capsys)
        _refused(code, err, *names)
    assert time.perf_counter() - t0 < 5
    assert not (tmp_path / "b").exists() and not (tmp_path / "s").exists()
    # the Python API: make_simulator and the registry check the seed up front, naming it
    for bad in (-5, 2**63, 1.5, True):
        with pytest.raises(InvalidInputError) as e:
            make_simulator("water2d", "mpm", seed=bad)
        assert e.value.field == "seed", str(e.value)
        with pytest.raises(InvalidInputError) as e:
            scene_spec("water2d", seed=bad)
        assert e.value.field == "seed"
    # every seed in range reaches k-means: one of 2^32 or more gets one derived from it, always the same
    assert kmeans_seed(7) == 7 and kmeans_seed(KMEANS_SEEDS - 1) == KMEANS_SEEDS - 1
    big = [kmeans_seed(s) for s in (KMEANS_SEEDS, 2**63 - 1)]
    assert all(0 <= k < KMEANS_SEEDS for k in big) and big == [kmeans_seed(s) for s in (KMEANS_SEEDS, 2**63 - 1)]
    x = np.random.default_rng(0).uniform(0.2, 0.8, (200, 2))
    assert np.array_equal(cluster_particles(x, 0.5, seed=2**63 - 1), cluster_particles(x, 0.5, seed=2**63 - 1))
    sim = make_simulator("water2d", "mpm", r_p=0.5, seed=2**63 - 1, threads=1)
    assert 0 < sim.scene.num_particles < make_simulator("water2d", "mpm", seed=2**63 - 1, threads=1).scene.num_particles


@pytest.mark.parametrize(
    "flag",
    [["--r-p", "1.0"], ["--r-c", repr(R_C)], ["--cheap", "neural"], ["--calibrated"], ["--model", "m.onnx"], ["--n-grid", "128"], ["--dwell", "3"]],
)
def test_a_configuration_flag_given_with_the_default_solver_is_refused_whatever_its_value(tmp_path, monkeypatch, capsys, flag):
    monkeypatch.chdir(tmp_path)  # --solver auto reads tuned/SCENE.json here
    out = tmp_path / "out"
    code, err = _cli(["simulate", "dam_break2d", *flag, "--frames", "1", "--out", str(out), "--no-render", "--quiet"], capsys)
    _refused(code, err, "solver", flag[0])
    assert not out.exists()
    if flag[0] in ("--r-p", "--model", "--calibrated"):  # --solver auto takes these from its tuned file
        code, err = _cli(["simulate", "dam_break2d", "--solver", "auto", *flag, "--out", str(out), "--quiet"], capsys)
        _refused(code, err, "solver", flag[0])


def test_a_corrupt_defaults_json_ends_in_one_line_naming_the_file(tmp_path, monkeypatch, capsys):
    import hybridmpm.models as models
    from hybridmpm.sim import default_settings

    class Files:
        @staticmethod
        def files(package: str) -> Path:
            return tmp_path

    monkeypatch.setattr(models, "resources", Files)
    monkeypatch.chdir(tmp_path)
    for text in ("{not json", "[1, 2]", '{"water2d": 3}', '{"water2d": {"config": {"kind": "rocket"}}}', '{"water2d": {"config": {"kind": "mpm"}}}'):
        (tmp_path / "defaults.json").write_text(text)
        with pytest.raises(InvalidInputError) as e:
            default_settings("water2d")
        assert e.value.field == "defaults" and "defaults.json" in str(e.value), str(e.value)
        code, err = _cli(["simulate", "water2d", "--frames", "1", "--out", str(tmp_path / "out"), "--no-render", "--quiet"], capsys)
        _refused(code, err, "defaults", "defaults.json")


def test_tune_refuses_an_unwritable_or_existing_out_and_a_work_that_is_no_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # whatever a broken build writes stays here
    existing = tmp_path / "existing.json"
    existing.write_text("{}")
    # links to the devices, not the devices: a build that wrote its file would replace the link, never /dev/full itself
    full, null = tmp_path / "full.json", tmp_path / "null"
    full.symlink_to("/dev/full")
    null.symlink_to("/dev/null")
    short = ["--frames", "2", "--warmup", "0", "--seeds", "1", "--no-variants", "--quiet"]
    t0 = time.perf_counter()
    for extra, names in (
        (["--out", str(full), "--work", "w"], ("out", "full.json", "character device")),
        (["--out", str(existing), "--work", "w"], ("out", "exists")),
        (["--out", str(tmp_path), "--work", "w"], ("out", "directory")),
        (["--out", "t.json", "--work", str(null)], ("work", "null")),
    ):
        code, err = _cli(["tune", "water2d", "--error-budget", "1", *extra, *short], capsys)
        _refused(code, err, *names)
    assert time.perf_counter() - t0 < 5
    assert existing.read_text() == "{}" and not (tmp_path / "t.json").exists() and not (tmp_path / "w").exists()
