"""Bad input ends in a clear error naming the field, with nothing lost."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from hybridmpm.errors import InvalidInputError
from hybridmpm.models import shipped_model
from hybridmpm.neural import METADATA_KEY, GnsRuntime


def _with_metadata(tmp: Path, edit) -> Path:  # type: ignore[no-untyped-def]
    import onnx

    m = onnx.load(str(shipped_model("water2d")))
    prop = next(p for p in m.metadata_props if p.key == METADATA_KEY)
    prop.value = edit(prop.value)
    out = tmp / "edited.onnx"
    onnx.save(m, str(out))
    return out


@pytest.mark.parametrize(
    "key, value",
    [
        ("r_p", float("nan")),
        ("r_p", 1.5),
        ("r_t", 0),
        ("r_t", 2.5),
        ("radius", -1.0),
        ("dim", 4),
        ("bounds", [[0, 1]]),
        ("t_in", "6"),
        ("particle_types", "water"),
    ],
)
def test_model_metadata_out_of_range_names_the_key(tmp_path, key, value):
    def edit(raw: str) -> str:
        meta = json.loads(raw)
        meta[key] = value
        return json.dumps(meta)

    with pytest.raises(InvalidInputError) as e:
        GnsRuntime(_with_metadata(tmp_path, edit))
    assert e.value.field == f"model.{key}"


@pytest.mark.parametrize("raw", ["{not json", "[1, 2]"])
def test_malformed_model_metadata_is_refused(tmp_path, raw):
    with pytest.raises(InvalidInputError) as e:
        GnsRuntime(_with_metadata(tmp_path, lambda _: raw))
    assert e.value.field == "model"


def test_a_missing_key_of_an_old_export_gets_its_default(tmp_path):
    def edit(raw: str) -> str:
        meta = json.loads(raw)
        del meta["t_in"]
        return json.dumps(meta)

    m = GnsRuntime(_with_metadata(tmp_path, edit))
    assert m.t_in == 6 and np.isfinite(m.r_p)


# ----------------------------------------------------------------------- CLI
def _cli(*argv: str) -> tuple[int, str]:
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "hybridmpm", *argv], capture_output=True, text=True, timeout=300)
    return r.returncode, r.stderr


@pytest.mark.parametrize(
    "argv, says",
    [
        (["simulate", "--seed", "-1"], "--seed"),
        (["generate", "water2d", "--trajectories", "3", "--split", "a,b", "--out", "{tmp}/g"], "split"),
        (["inspect", "{tmp}/missing"], "no such dataset directory"),
        (["inspect", "{tmp}"], "metadata.json"),
        (["simulate", "--frames", "4", "--out", "{tmp}/file"], "out: "),
        (["simulate", "--frames", "4", "--out", "/proc/hybridmpm-nope"], "out: cannot write"),
        (["simulate", "nope", "--out", "{tmp}/o"], "nope"),
    ],
)
def test_the_cli_says_what_is_wrong_in_one_line(tmp_path, argv, says):
    (tmp_path / "file").write_text("not a directory")
    rc, err = _cli(*[a.replace("{tmp}", str(tmp_path)) for a in argv])
    assert rc != 0 and "Traceback" not in err
    assert says in err.strip().splitlines()[-1]  # one line says it (argparse prints its usage before)


def test_generate_with_a_bad_seed_writes_nothing(tmp_path):
    from hybridmpm.train.datasets import GenerateConfig, generate_dataset

    with pytest.raises(InvalidInputError) as e:
        generate_dataset(GenerateConfig("water2d", 3, frames=4, seed=-1), tmp_path / "g", progress=False)
    assert e.value.field == "seed" and not (tmp_path / "g").exists()


def test_debug_shows_the_traceback(tmp_path):
    rc, err = _cli("simulate", "nope", "--out", str(tmp_path), "--debug")
    assert rc != 0 and "Traceback" in err


def test_summary_json_is_strict_json(tmp_path):
    from hybridmpm.cli import main

    assert main(["simulate", "water2d", "--frames", "8", "--out", str(tmp_path), "--quiet", "--no-render", "--threads", "1"]) == 0
    text = (tmp_path / "summary.json").read_text()
    json.loads(text, parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))


def test_inspect_checks_a_dataset_against_its_metadata(tmp_path, capsys):
    from hybridmpm.cli import main
    from hybridmpm.train.datasets import GenerateConfig, generate_dataset

    d = tmp_path / "ds"
    generate_dataset(GenerateConfig("water2d", 3, frames=6), d, workers=1, progress=False)
    assert main(["inspect", str(d)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["problems"] == [] and all(v["sha256_checked"] for v in info["splits"].values())
    meta_path = d / "metadata.json"
    meta = json.loads(meta_path.read_text())

    def broken(**change):  # type: ignore[no-untyped-def]
        meta_path.write_text(json.dumps({**meta, **change}))
        rc = main(["inspect", str(d)])
        out = capsys.readouterr()
        return rc, json.loads(out.out)["problems"], out.err

    rc, problems, err = broken(sequence_length=5)
    assert rc == 1 and any("sequence_length 5" in p for p in problems) and "problem" in err
    rc, problems, _ = broken(sha256={**meta["sha256"], "valid": "0" * 64})
    assert rc == 1 and any(p.startswith("valid.npz: sha256") for p in problems)
    rc, problems, _ = broken(bounds=[[0.4, 0.6], [0.4, 0.6]])
    assert rc == 1 and any("outside bounds" in p for p in problems)
    meta_path.write_text(json.dumps(meta))
    (d / "test.npz").unlink()
    rc, problems, _ = broken()
    assert rc == 1 and any("'test' is missing" in p for p in problems)


# ------------------------------------------------------------ atomic restore
def _malformed(st: dict) -> list[tuple[str, dict]]:
    neural = st["neural"]
    bad_hist = None if neural["history"] is None else neural["history"][:, :-1]
    return [
        ("solver banana", {**st, "solver_name": "banana"}),
        ("buffer shape", {**st, "buffer": st["buffer"][:, :-1]}),
        ("buffer NaN-free but 4D", {**st, "buffer": st["buffer"][None]}),
        ("negative counter", {**st, "calm": -1}),
        ("neural history shape", {**st, "neural": {**neural, "history": bad_hist if bad_hist is not None else np.zeros((2, 2, 2))}}),
        ("mpm blob", {**st, "mpm": {**st["mpm"], "solver": b"garbage"}}),
        ("stats", {**st, "stats": {"steps": "x"}}),
        ("missing key", {k: v for k, v in st.items() if k != "last_score"}),
    ]


def test_a_malformed_hybrid_state_changes_nothing():
    from hybridmpm.scenes import make_scene
    from hybridmpm.sim import HybridSimulator, rollout

    sim = HybridSimulator(make_scene("water2d", seed=1000), mpm_threads=1)
    rollout(sim, 60)  # on the network by now
    good = sim.state()
    for name, bad in _malformed(good):
        with pytest.raises(InvalidInputError) as e:
            sim.restore(bad)
        assert e.value.field == "state", name
    a = rollout(sim, 40)  # continues exactly as from the untouched state
    sim.restore(good)
    b = rollout(sim, 40)
    assert np.array_equal(a.positions, b.positions) and np.array_equal(a.solver, b.solver)


# ------------------------------------------------------------- memory budget
@pytest.fixture
def small_budget():
    from hybridmpm.limits import set_memory_budget

    set_memory_budget("64M")
    yield 64 * 2**20
    set_memory_budget(None)


def test_sizes_parse_and_the_environment_sets_the_budget(monkeypatch):
    from hybridmpm.limits import ENV_VAR, memory_budget, parse_size, physical_memory

    assert parse_size("8G") == 8 * 2**30 and parse_size("512M") == 512 * 2**20 and parse_size("1.5k") == 1536 and parse_size(100) == 100
    for bad in ("lots", "-1G", "0", ""):
        with pytest.raises(InvalidInputError):
            parse_size(bad)
    monkeypatch.setenv(ENV_VAR, "3G")
    assert memory_budget() == 3 * 2**30
    monkeypatch.delenv(ENV_VAR)
    assert memory_budget() == physical_memory() // 2


def test_a_scene_too_large_for_the_budget_is_refused_before_it_is_built(tmp_path, small_budget):
    import resource

    from hybridmpm.scenes import SceneSpec

    spec = tmp_path / "big.toml"
    spec.write_text('name = "big"\ndim = 2\nn_grid = 4096\n[[blocks]]\nlo = [0.1, 0.1]\nhi = [0.5, 0.5]\nmaterial = "water"\n')
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(InvalidInputError) as e:
        SceneSpec.load(spec).build()
    assert e.value.field == "blocks[0]" and "particles" in str(e.value) and "memory budget" in str(e.value)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 64 * 1024  # kB: nothing large was allocated


def test_a_binary_or_huge_scene_file_is_refused(tmp_path):
    from hybridmpm.scenes import SceneSpec

    (tmp_path / "bin.toml").write_bytes(bytes(range(256)) * 4)
    with pytest.raises(InvalidInputError, match="not a text file") as e:
        SceneSpec.load(tmp_path / "bin.toml")
    assert e.value.field == "scene"
    with open(tmp_path / "huge.json", "wb") as f:
        f.truncate(64 * 2**20)  # sparse: no disk used
    with pytest.raises(InvalidInputError, match="bytes") as e:
        SceneSpec.load(tmp_path / "huge.json")
    assert e.value.field == "scene"


def test_a_rollout_beyond_the_budget_is_refused_before_any_step(small_budget):
    from hybridmpm.scenes import make_scene
    from hybridmpm.sim import MpmSimulator, rollout

    sim = MpmSimulator(make_scene("water2d", seed=1), threads=1)
    with pytest.raises(InvalidInputError) as e:
        rollout(sim, 10**7)
    assert e.value.field == "frames" and sim.step_index == 0
    assert rollout(sim, 4).frames_done == 4  # a small one still runs


def test_generate_beyond_the_budget_writes_nothing(tmp_path, small_budget):
    from hybridmpm.train.datasets import GenerateConfig, generate_dataset

    with pytest.raises(InvalidInputError) as e:
        generate_dataset(GenerateConfig("water2d", 3, frames=10**7), tmp_path / "g", progress=False)
    assert e.value.field == "frames" and not (tmp_path / "g").exists()


def test_a_grid_mass_grid_beyond_the_budget_is_refused_by_dimension(small_budget):
    from hybridmpm.metrics import grid_mass_error

    x2 = np.random.default_rng(0).random((1, 50, 2)).astype(np.float32)
    x3 = np.random.default_rng(0).random((1, 50, 3)).astype(np.float32)
    assert grid_mass_error(x2, x2, 1024)[0] == 0.0  # 1024² fits in 64 MiB
    with pytest.raises(InvalidInputError) as e:
        grid_mass_error(x3, x3, 1024)  # 1024³ does not
    assert e.value.field == "n_grid" and "memory budget" in str(e.value)


@pytest.mark.parametrize(
    "obstacle, field",
    [
        ({"shape": "box", "center": [0.6, 0.3], "half_extents": [0.1, 0.02], "angle_deg": float("nan")}, "obstacles[0].angle_deg"),
        ({"shape": "box", "center": [0.6, 0.3], "half_extents": [0.1, 0.02], "rotation": [[1, 0], [0, 2]]}, "obstacles[0].rotation"),
        ({"shape": "sphere", "center": [0.6, 0.3], "radius": float("inf")}, "obstacles[0].radius"),
        ({"shape": "box", "center": [0.6, "x"], "half_extents": [0.1, 0.02]}, "obstacles[0].center"),
    ],
)
def test_a_bad_obstacle_names_its_field(obstacle, field):
    from hybridmpm.scenes import SceneSpec

    base = {"name": "t", "dim": 2, "blocks": [{"lo": [0.1, 0.1], "hi": [0.3, 0.3], "material": "water"}]}
    with pytest.raises(InvalidInputError) as e:
        SceneSpec.from_dict({**base, "obstacles": [obstacle]}).build()
    assert e.value.field == field
