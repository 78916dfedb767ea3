"""GNS dataset I/O (hybridmpm.data.gns) against the public layout and brute force.

The reference reader below is written from the public description of the
layout (geoelements/gns ``data_loader``: ``np.load(path, allow_pickle=True)``,
the ``gns_data`` member or every item, then ``item[0]``, ``item[1]``), not
from our reader.
"""

from __future__ import annotations

import builtins
import hashlib
import io
import json
import os
import pickle
import zipfile
from pathlib import Path

import numpy as np
import pytest

from hybridmpm.data import (
    GnsDataset,
    GnsTrajectory,
    SplitNotFoundError,
    compute_statistics,
    gns,
    read_metadata,
    read_split,
    write_metadata,
    write_split,
)
from hybridmpm.errors import InvalidInputError


def _trajectories(rng: np.random.Generator, dim: int, n_traj: int = 3) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {}
    for i in range(n_traj):
        t, n = 5 + i, 8 + 2 * i
        positions = rng.random((t, n, dim), dtype=np.float32)
        particle_type = rng.choice(np.array([3, 5, 6]), size=n).astype(np.int64)
        out[f"simulation_trajectory_{i}"] = (positions, particle_type)
    return out


def _reference_read(path: Path) -> tuple[list[str], list[tuple[np.ndarray, np.ndarray]]]:
    """The public idiom of geoelements/gns, independent of hybridmpm."""
    with np.load(path, allow_pickle=True) as f:
        keys = list(f.keys())
        data = f["gns_data"] if "gns_data" in f else [item for _, item in f.items()]
        pairs = [(item[0], item[1]) for item in data]
    return keys, pairs


def _object_item(*elems: object) -> np.ndarray:
    item = np.empty(len(elems), dtype=object)
    for i, e in enumerate(elems):
        item[i] = e
    return item


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _metadata(d: int, /, **overrides: object) -> dict:
    meta = {
        "bounds": [[0.0, 1.0]] * d,
        "sequence_length": 4,
        "default_connectivity_radius": 0.015,
        "dim": d,
        "dt": 0.0025,
        "vel_mean": [0.0] * d,
        "vel_std": [1.0] * d,
        "acc_mean": [0.0] * d,
        "acc_std": [1.0] * d,
    }
    meta.update(overrides)
    return meta


# --------------------------------------------------------------------------- round trip and interop


@pytest.mark.parametrize("dim", [2, 3])
def test_round_trip_is_exact(tmp_path: Path, dim: int) -> None:
    data = _trajectories(np.random.default_rng(dim), dim)
    material = np.array([0.5, 30.0])
    data_with_material = {**data, "with_material": (*data["simulation_trajectory_0"], material)}
    path = tmp_path / "train.npz"
    write_split(path, data_with_material)

    back = read_split(path)
    assert list(back) == sorted(data_with_material)
    for tid, (positions, particle_type) in data.items():
        got = back[tid]
        assert isinstance(got, GnsTrajectory)
        assert got.positions.dtype == np.float32 and got.particle_type.dtype == np.int64
        np.testing.assert_array_equal(got.positions, positions)
        np.testing.assert_array_equal(got.particle_type, particle_type)
        assert got.material_properties is None
    np.testing.assert_array_equal(back["with_material"].material_properties, material)
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]


@pytest.mark.parametrize("dim", [2, 3])
def test_public_reader_reads_our_files(tmp_path: Path, dim: int) -> None:
    data = _trajectories(np.random.default_rng(10 + dim), dim)
    # float64 / int32 inputs are stored as the layout's float32 / int64
    data["simulation_trajectory_1"] = (data["simulation_trajectory_1"][0].astype(np.float64), data["simulation_trajectory_1"][1].astype(np.int32))
    write_split(tmp_path / "train.npz", data)

    keys, pairs = _reference_read(tmp_path / "train.npz")
    assert keys == sorted(data)
    for key, (positions, particle_type) in zip(keys, pairs):
        assert positions.dtype == np.float32 and particle_type.dtype == np.int64
        assert positions.shape == data[key][0].shape and particle_type.shape == (positions.shape[1],)
        np.testing.assert_array_equal(positions, data[key][0].astype(np.float32))
        np.testing.assert_array_equal(particle_type, data[key][1])

    stats = compute_statistics(read_split(tmp_path / "train.npz"))
    write_metadata(tmp_path / "metadata.json", _metadata(dim, **stats, sequence_length=4, extra_key={"kept": True}))
    meta = json.loads((tmp_path / "metadata.json").read_text())
    assert isinstance(meta["dim"], int) and meta["dim"] == dim
    assert isinstance(meta["sequence_length"], int)
    for key in ("dt", "default_connectivity_radius"):
        assert isinstance(meta[key], float) and meta[key] > 0
    assert np.array(meta["bounds"], dtype=float).shape == (dim, 2)
    for key in ("vel_mean", "vel_std", "acc_mean", "acc_std"):
        assert isinstance(meta[key], list) and len(meta[key]) == dim
        assert all(isinstance(x, float) for x in meta[key])
    assert meta["extra_key"] == {"kept": True}
    assert read_metadata(tmp_path / "metadata.json") == meta


@pytest.mark.parametrize("savez", [np.savez, np.savez_compressed])
def test_reads_files_of_plain_numpy_savez(tmp_path: Path, savez) -> None:
    rng = np.random.default_rng(3)
    pos0, pos1 = rng.random((4, 6, 2)), rng.random((3, 5, 2)).astype(np.float32)  # float64 is cast on read
    type0, type1 = np.full(6, 5, dtype=np.int32), np.array([6, 6, 6, 3, 3])
    path = tmp_path / "foreign.npz"
    savez(path, simulation_trajectory_0=_object_item(pos0, type0), simulation_trajectory_1=_object_item(pos1, type1, np.array([0.3])))

    back = read_split(path)
    assert list(back) == ["simulation_trajectory_0", "simulation_trajectory_1"]
    np.testing.assert_array_equal(back["simulation_trajectory_0"].positions, pos0.astype(np.float32))
    assert back["simulation_trajectory_0"].particle_type.dtype == np.int64
    np.testing.assert_array_equal(back["simulation_trajectory_0"].particle_type, type0)
    np.testing.assert_array_equal(back["simulation_trajectory_1"].positions, pos1)
    np.testing.assert_array_equal(back["simulation_trajectory_1"].material_properties, [0.3])


def test_reads_the_gns_data_variant(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    tuples = [(rng.random((3 + i, 4, 3)).astype(np.float32), np.full(4, 6), np.float64(20.0 + i)) for i in range(11)]
    structured = np.empty(len(tuples), dtype=object)
    for i, value in enumerate(tuples):
        structured[i] = value
    path = tmp_path / "gns_data.npz"
    np.savez_compressed(path, gns_data=structured)

    back = read_split(path)
    assert list(back) == [f"simulation_trajectory_{i:02d}" for i in range(11)]
    for (positions, particle_type, friction), got in zip(tuples, back.values()):
        np.testing.assert_array_equal(got.positions, positions)
        np.testing.assert_array_equal(got.particle_type, particle_type)
        assert got.material_properties is not None and float(got.material_properties) == friction


def _npz_with_pickled_member(path: Path, obj: object, protocol: int, *, numpy1_names: bool = False) -> None:
    payload = pickle.dumps(obj, protocol=protocol)
    if numpy1_names:
        assert b"numpy._core" in payload
        payload = payload.replace(b"numpy._core.", b"numpy.core.")
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "|O", "fortran_order": False, "shape": (len(obj),)})  # type: ignore[arg-type]
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("simulation_trajectory_0.npy", buf.getvalue() + payload)


@pytest.mark.parametrize("protocol", [2, 3, 4, 5])
def test_reads_every_pickle_protocol_and_numpy1_names(tmp_path: Path, protocol: int) -> None:
    positions = np.random.default_rng(5).random((3, 4, 2)).astype(np.float32)
    item = _object_item(positions, np.arange(4))
    for numpy1 in (False, True):
        if numpy1 and protocol >= 4:
            continue  # protocol 4+ frames the names; the text GLOBAL of 2/3 is enough to cover numpy 1.x spellings
        path = tmp_path / f"p{protocol}_{numpy1}.npz"
        _npz_with_pickled_member(path, item, protocol, numpy1_names=numpy1)
        got = read_split(path)["simulation_trajectory_0"]
        np.testing.assert_array_equal(got.positions, positions)
        np.testing.assert_array_equal(got.particle_type, np.arange(4))


def test_writes_are_byte_deterministic(tmp_path: Path) -> None:
    data = _trajectories(np.random.default_rng(6), 2, n_traj=4)
    write_split(tmp_path / "a.npz", data)
    write_split(tmp_path / "b.npz", dict(reversed(list(data.items()))))  # insertion order does not matter
    assert _sha256(tmp_path / "a.npz") == _sha256(tmp_path / "b.npz")
    with zipfile.ZipFile(tmp_path / "a.npz") as zf:
        assert [i.filename for i in zf.infolist()] == [f"{k}.npy" for k in sorted(data)]
        assert {i.date_time for i in zf.infolist()} == {(1980, 1, 1, 0, 0, 0)}
        assert {i.compress_type for i in zf.infolist()} == {zipfile.ZIP_STORED}
    write_split(tmp_path / "z1.npz", data, compress=True)
    write_split(tmp_path / "z2.npz", data, compress=True)
    assert _sha256(tmp_path / "z1.npz") == _sha256(tmp_path / "z2.npz")
    with zipfile.ZipFile(tmp_path / "z1.npz") as zf:
        assert {i.compress_type for i in zf.infolist()} == {zipfile.ZIP_DEFLATED}
    assert read_split(tmp_path / "z1.npz").keys() == data.keys()
    positions, particle_type = data["simulation_trajectory_2"]
    changed = positions.copy()
    changed[1, 2, 0] = np.nextafter(changed[1, 2, 0], np.float32(2))
    write_split(tmp_path / "c.npz", {**data, "simulation_trajectory_2": (changed, particle_type)})
    assert _sha256(tmp_path / "c.npz") != _sha256(tmp_path / "a.npz")


# --------------------------------------------------------------------------- statistics


def _brute_force_statistics(trajectories: list[tuple[np.ndarray, np.ndarray]], excluded: tuple[int, ...]) -> dict[str, np.ndarray]:
    vel, acc = [], []
    for positions, particle_type in trajectories:
        p = positions.astype(np.float64)[:, ~np.isin(particle_type, excluded)]
        vel.append((p[1:] - p[:-1]).reshape(-1, p.shape[-1]))
        acc.append((p[2:] - 2 * p[1:-1] + p[:-2]).reshape(-1, p.shape[-1]))
    v, a = np.concatenate(vel), np.concatenate(acc)
    return {"vel_mean": v.mean(0), "vel_std": v.std(0), "acc_mean": a.mean(0), "acc_std": a.std(0)}


@pytest.mark.parametrize("chunk", [3, 256])
def test_statistics_equal_brute_force_and_exclude_kinematic(monkeypatch: pytest.MonkeyPatch, chunk: int) -> None:
    monkeypatch.setattr(gns.statistics, "_STATS_CHUNK_FRAMES", chunk)  # 3 frames per chunk exercises the chunk seams
    rng = np.random.default_rng(7)
    trajectories = []
    for t, n in [(9, 12), (10, 7), (11, 20), (2, 5)]:  # the T = 2 trajectory has velocities but no acceleration
        steps = rng.normal(0.01, 0.002, (t, n, 2)).astype(np.float32)
        positions = (0.3 + np.cumsum(steps, axis=0)).astype(np.float32)
        particle_type = np.where(np.arange(n) % 4 == 0, 3, 5)
        positions[:, particle_type == 3] *= 50.0  # kinematic particles move very differently
        trajectories.append((positions, particle_type))

    stats = compute_statistics({f"t{i}": tr for i, tr in enumerate(trajectories)})
    expected = _brute_force_statistics(trajectories, (3,))
    for key, value in expected.items():
        np.testing.assert_allclose(stats[key], value, rtol=1e-9, atol=1e-15, err_msg=key)

    with_kinematic = compute_statistics(trajectories, exclude_types=())
    everything = _brute_force_statistics(trajectories, ())
    for key, value in everything.items():
        np.testing.assert_allclose(with_kinematic[key], value, rtol=1e-9, atol=1e-15, err_msg=key)
    assert not np.allclose(with_kinematic["vel_std"], stats["vel_std"])


def test_statistics_need_accelerations() -> None:
    with pytest.raises(InvalidInputError) as err:
        compute_statistics([(np.zeros((2, 3, 2), np.float32), np.full(3, 5))])
    assert err.value.field == "trajectories"
    with pytest.raises(InvalidInputError):
        compute_statistics([(np.zeros((5, 3, 2), np.float32), np.full(3, 3))])  # all kinematic


# --------------------------------------------------------------------------- hostile and malformed input


class _RunsShell:
    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self):
        return (os.system, (self.command,))


class _RunsEval:
    def __reduce__(self):
        return (builtins.eval, ("1 + 1",))


def test_restricted_unpickler_refuses_code(tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    path = tmp_path / "evil.npz"
    np.savez(path, simulation_trajectory_0=_object_item(_RunsShell(f"touch '{marker}'"), np.zeros(1, np.int64)))

    with pytest.raises(InvalidInputError) as err:
        read_split(path)
    assert "system" in str(err.value) and "evil.npz" in str(err.value)
    assert err.value.field == "simulation_trajectory_0"
    assert not marker.exists()

    # Control: the payload is live; an unrestricted load does run it.
    with np.load(path, allow_pickle=True) as f:
        f["simulation_trajectory_0"]
    assert marker.exists()

    np.savez(tmp_path / "eval.npz", gns_data=_object_item((_RunsEval(), np.zeros(1))))
    with pytest.raises(InvalidInputError, match="eval"):
        read_split(tmp_path / "eval.npz")


def test_not_a_zip_and_truncated_or_corrupt_files(tmp_path: Path) -> None:
    (tmp_path / "text.npz").write_bytes(b"this is not a zip file at all")
    with pytest.raises(InvalidInputError) as err:
        read_split(tmp_path / "text.npz")
    assert err.value.field == "path" and "text.npz" in str(err.value)

    good = tmp_path / "good.npz"
    write_split(good, _trajectories(np.random.default_rng(8), 2))
    blob = good.read_bytes()
    (tmp_path / "truncated.npz").write_bytes(blob[: len(blob) // 2])
    with pytest.raises(InvalidInputError, match="truncated.npz"):
        read_split(tmp_path / "truncated.npz")

    corrupt = bytearray(blob)
    with zipfile.ZipFile(good) as zf:
        first = zf.infolist()[0]
    start = first.header_offset + 30 + len(first.filename)  # first member's compressed data
    for i in range(start + 5, start + 25):
        corrupt[i] ^= 0xFF
    (tmp_path / "corrupt.npz").write_bytes(bytes(corrupt))
    with pytest.raises(InvalidInputError) as err:
        read_split(tmp_path / "corrupt.npz")
    assert err.value.field == "simulation_trajectory_0"


def test_malformed_trajectories_name_the_field(tmp_path: Path) -> None:
    rng = np.random.default_rng(9)
    positions, particle_type = rng.random((4, 5, 2)).astype(np.float32), np.full(5, 5)
    nan_positions = positions.copy()
    nan_positions[2, 3, 1] = np.nan
    cases = {
        "positions": (positions[0], particle_type),  # 2-D
        "particle_type": (positions, np.full(4, 5)),  # length mismatch
        "nan": (nan_positions, particle_type),
    }
    fields = {"positions": "positions", "particle_type": "particle_type", "nan": "positions"}
    for name, value in cases.items():
        foreign = tmp_path / f"{name}.npz"
        np.savez_compressed(foreign, simulation_trajectory_0=_object_item(*value))
        with pytest.raises(InvalidInputError) as err:
            read_split(foreign)
        assert err.value.field == f"simulation_trajectory_0.{fields[name]}", name
        assert f"{name}.npz" in str(err.value) and "simulation_trajectory_0" in str(err.value)

        with pytest.raises(InvalidInputError) as err:
            write_split(tmp_path / f"ours_{name}.npz", {"simulation_trajectory_0": value})
        assert err.value.field == f"simulation_trajectory_0.{fields[name]}", name
        assert not (tmp_path / f"ours_{name}.npz").exists()

    with pytest.raises(InvalidInputError) as err:
        write_split(tmp_path / "bad_id.npz", {"a/b": (positions, particle_type)})
    assert err.value.field == "trajectory_id"
    with pytest.raises(InvalidInputError) as err:
        write_split(tmp_path / "float_types.npz", {"t": (positions, particle_type.astype(np.float64))})
    assert err.value.field == "t.particle_type"
    assert [p for p in os.listdir(tmp_path) if p.startswith("ours_") or p.endswith(".tmp")] == []


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"dt": None}, "dt"),
        ({"bounds": [[0.0, 1.0]] * 3}, "bounds"),
        ({"bounds": [[1.0, 0.0], [0.0, 1.0]]}, "bounds"),
        ({"vel_std": [1.0]}, "vel_std"),
        ({"acc_mean": [0.0, float("nan")]}, "acc_mean"),
        ({"dim": 4}, "dim"),
        ({"sequence_length": 2.5}, "sequence_length"),
        ({"default_connectivity_radius": -1.0}, "default_connectivity_radius"),
    ],
)
def test_malformed_metadata_names_the_field(tmp_path: Path, change: dict, field: str) -> None:
    meta = _metadata(2, **change)
    if meta["dt"] is None:
        del meta["dt"]
    path = tmp_path / "metadata.json"
    path.write_text(json.dumps(meta))
    with pytest.raises(InvalidInputError) as err:
        read_metadata(path)
    assert err.value.field == field and field in str(err.value)
    with pytest.raises(InvalidInputError) as err:
        write_metadata(tmp_path / "out.json", meta)
    assert err.value.field == field
    assert not (tmp_path / "out.json").exists()


# --------------------------------------------------------------------------- dataset directory


def test_dataset_directory(tmp_path: Path) -> None:
    data = _trajectories(np.random.default_rng(11), 2)
    write_split(tmp_path / "train.npz", data)
    write_split(tmp_path / "test.npz", {"simulation_trajectory_0": data["simulation_trajectory_0"]})
    write_metadata(tmp_path / "metadata.json", _metadata(2, **compute_statistics(data)))

    ds = GnsDataset(tmp_path)
    assert ds.metadata["dim"] == 2 and len(ds) == 2 and list(ds) == ["train", "test"]
    assert list(ds.split("train")) == sorted(data)
    np.testing.assert_array_equal(ds["test"]["simulation_trajectory_0"].positions, data["simulation_trajectory_0"][0])
    with pytest.raises(SplitNotFoundError) as err:
        ds.split("valid")
    assert "train, test" in str(err.value) and err.value.field == "name"
    assert isinstance(err.value, KeyError) and isinstance(err.value, InvalidInputError)
    assert ds.get("valid") is None and "valid" not in ds

    write_split(tmp_path / "valid.npz", _trajectories(np.random.default_rng(12), 3, n_traj=1))
    with pytest.raises(InvalidInputError) as dim_err:
        ds.split("valid")
    assert dim_err.value.field == "simulation_trajectory_0.positions" and "dim" in str(dim_err.value)
