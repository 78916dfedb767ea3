"""Hostile trajectory files end in one line naming the array or field, before
anything large is allocated: every array of a trajectory ``.npz`` is sized
from its ``.npy`` header against the memory budget before it is read (one
declaring 112 GiB in a few kilobytes, one holding more than the budget);
``scene_params`` is depth-checked by the one JSON helper before it is
parsed; a ``dt_frame`` that makes the frames' velocities overflow is refused
naming ``dt_frame``, so no export holds an infinite value."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import zipfile

import numpy as np
import pytest

from hybridmpm.cli import main
from hybridmpm.errors import InvalidInputError
from hybridmpm.files import MAX_NESTING, loads_json
from hybridmpm.trajectory import Trajectory

GOOD = {
    "positions": np.random.default_rng(0).uniform(0.2, 0.8, (3, 50, 3)).astype(np.float32),
    "particle_type": np.full(50, 5),
    "dt_frame": np.float64(2.5e-3),
}


def _npy_header(shape, dtype="<f4"):
    """An .npy version 1.0 header declaring ``shape`` of ``dtype`` (what np.save writes before the data)."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": dtype, "fortran_order": False, "shape": tuple(shape)})
    return buf.getvalue()


def _write(path, members):
    """A zip of raw ``.npy`` members: name -> bytes (stored deflated)."""
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        for name, data in members.items():
            with z.open(name + ".npy", "w", force_zip64=True) as f:
                if isinstance(data, bytes):
                    f.write(data)
                else:  # (header, zero bytes to write after it)
                    head, zeros = data
                    f.write(head)
                    chunk = bytes(1 << 24)
                    while zeros > 0:
                        f.write(chunk[: min(zeros, len(chunk))])
                        zeros -= len(chunk)
    return path


def _arrays(**arrays):
    out = {}
    for k, v in arrays.items():
        buf = io.BytesIO()
        np.save(buf, np.asarray(v), allow_pickle=False)
        out[k] = buf.getvalue()
    return out


def _cli(argv, capsys):
    code = main(argv)
    err = capsys.readouterr().err.strip()
    return code, err


def test_a_few_kilobytes_declaring_112_gib_are_refused_naming_the_array(tmp_path, capsys):
    declared = (1, 10_000_000_000, 3)  # float32: 112 GiB
    path = _write(tmp_path / "huge.npz", {**_arrays(particle_type=GOOD["particle_type"], dt_frame=GOOD["dt_frame"]), "positions": _npy_header(declared)})
    assert path.stat().st_size < 100_000
    with pytest.raises(InvalidInputError) as e:
        Trajectory.load(path)
    assert e.value.field == "positions" and "GiB" in str(e.value), str(e.value)
    code, err = _cli(["export", str(path), "--points", "ply", "--out", str(tmp_path / "out")], capsys)
    assert code == 2 and len(err.splitlines()) == 1 and "positions" in err, err
    # an extra declaring as much is refused as well, by its name
    path = _write(tmp_path / "extra.npz", {**_arrays(**GOOD), "junk": _npy_header((1 << 40,), "<f8")})
    with pytest.raises(InvalidInputError) as e:
        Trajectory.load(path)
    assert e.value.field == "junk", str(e.value)


def test_a_file_holding_more_than_the_budget_is_refused_before_it_is_read(tmp_path):
    """128 MiB of zeros (about 130 kB deflated) under a 64 MiB budget: refused in one line naming positions,
    the command's peak memory growing less than the budget (reading the array would take 128 MiB)."""
    n = 128 * 2**20 // 12
    path = _write(
        tmp_path / "zeros.npz",
        {**_arrays(particle_type=np.full(n, 5, np.int8), dt_frame=GOOD["dt_frame"]), "positions": (_npy_header((1, n, 3)), n * 12)},
    )
    assert path.stat().st_size < 2 * 2**20
    code = (
        "import resource, sys\n"
        "from hybridmpm.cli import main\n"
        "import hybridmpm.trajectory, hybridmpm.cli.export\n"
        "before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss\n"
        "rc = main(sys.argv[1:])\n"
        "print((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) * 1024)\n"
        "sys.exit(rc)\n"
    )
    env_budget = {"HYBRIDMPM_MEMORY_BUDGET": "64M"}
    r = subprocess.run(
        [sys.executable, "-c", code, "export", str(path), "--points", "ply", "--out", str(tmp_path / "out")],
        capture_output=True,
        text=True,
        env={**os.environ, **env_budget},
        timeout=120,
    )
    growth = int(r.stdout.strip().splitlines()[-1])  # of the peak over the command, its imports done
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "positions" in lines[0] and "memory budget" in lines[0], r.stderr[-2000:]
    assert growth < 64 * 2**20, f"the peak RSS grew {growth / 2**20:.0f} MiB: the array was read"


def test_a_deep_scene_params_is_refused_in_one_line(tmp_path, capsys):
    deep = "[" * 100_000 + "]" * 100_000
    path = tmp_path / "deep.npz"
    np.savez(path, **GOOD, scene_params=np.asarray(deep))
    code, err = _cli(["export", str(path), "--points", "ply", "--out", str(tmp_path / "out")], capsys)
    assert code == 2 and len(err.splitlines()) == 1 and "scene_params" in err and str(MAX_NESTING) in err, err
    # the helper itself: depth checked before parsing, the field named; a string's brackets do not count
    with pytest.raises(InvalidInputError) as e:
        loads_json(deep, "scene_params")
    assert e.value.field == "scene_params"
    assert loads_json(json.dumps({"a": "[" * 1000}), "x") == {"a": "[" * 1000}
    with pytest.raises(InvalidInputError) as e:
        loads_json("{not json", "scene_params")
    assert e.value.field == "scene_params"


def test_a_dt_frame_that_makes_the_velocities_infinite_is_refused(tmp_path, capsys):
    path = tmp_path / "tiny_dt.npz"
    np.savez(path, **{**GOOD, "dt_frame": np.float64(1e-300)})
    with pytest.raises(InvalidInputError) as e:
        Trajectory.load(path)
    assert e.value.field == "dt_frame", str(e.value)
    for kind in (["--points", "ply"], ["--usd"]):
        code, err = _cli(["export", str(path), *kind, "--out", str(tmp_path / "out")], capsys)
        assert code == 2 and len(err.splitlines()) == 1 and "dt_frame" in err, err
    # a still trajectory has no velocity to overflow; the same dt_frame is fine there
    still = np.repeat(GOOD["positions"][:1], 3, axis=0)
    assert Trajectory(still, GOOD["particle_type"], 1e-300).dt_frame == 1e-300
    # write_usd's own check, for arrays handed to it directly
    from hybridmpm.render.usd import write_usd

    with pytest.raises(InvalidInputError) as e:
        write_usd(tmp_path / "run.usd", GOOD["positions"], GOOD["particle_type"], 1e-300)
    assert e.value.field == "dt_frame"
