"""Files a user or an attacker hands us — scene files, sketch files, store
records, uploaded checkpoints — are opened only if they are regular files,
sized on the open file before any read, parsed only to a bounded depth, and
refused with an error naming the field: never a hang, a traceback or an
unbounded read. Scene building is linear in its blocks."""

from __future__ import annotations

import io
import json
import os
import struct
import threading
import time
import warnings
import zipfile
from pathlib import Path

import numpy as np
import pytest

from hybridmpm import files
from hybridmpm.control.sketch import Sketch
from hybridmpm.errors import InvalidInputError
from hybridmpm.files import MAX_NESTING, check_nesting, read_regular_file
from hybridmpm.scenes import SceneSpec
from hybridmpm.scenes.spec import MAX_BLOCKS


def _field_within(fn, seconds: float = 10.0) -> str:
    """The field of the InvalidInputError ``fn`` raises, which it must raise within ``seconds`` (never hang)."""
    out: dict = {}

    def run() -> None:
        try:
            fn()
        except InvalidInputError as e:
            out["field"] = e.field
        except BaseException as e:  # noqa: BLE001 - the test reports what else came out
            out["other"] = e

    t = threading.Thread(target=run, daemon=True)
    t.start()
    t.join(seconds)
    assert not t.is_alive(), f"still running after {seconds} s"
    assert "other" not in out, repr(out.get("other"))
    assert "field" in out, "nothing was refused"
    return out["field"]


def test_only_regular_files_are_read_and_their_size_is_checked_before_reading(tmp_path: Path):
    fifo = tmp_path / "scene.json"
    os.mkfifo(fifo)
    assert _field_within(lambda: SceneSpec.load(fifo)) == "scene"
    zero = tmp_path / "zero.json"
    zero.symlink_to("/dev/zero")
    assert _field_within(lambda: SceneSpec.load(zero)) == "scene"
    assert _field_within(lambda: SceneSpec.load(tmp_path)) == "scene"  # a directory
    sparse = tmp_path / "sparse.toml"
    with open(sparse, "wb") as f:
        f.truncate(3 << 30)  # 3 GiB, no blocks on disk: refused from fstat, never read
    t0 = time.perf_counter()
    assert _field_within(lambda: SceneSpec.load(sparse)) == "scene"
    assert time.perf_counter() - t0 < 2.0
    ok = tmp_path / "ok.bin"
    ok.write_bytes(b"x" * 100)
    assert read_regular_file(ok, 100, "f") == b"x" * 100
    with pytest.raises(InvalidInputError, match="101|100"):
        read_regular_file(ok, 99, "f")
    link = tmp_path / "link.bin"
    link.symlink_to(ok)  # a link to a regular file is fine
    assert read_regular_file(link, 100, "f") == b"x" * 100


@pytest.mark.parametrize("suffix", [".json", ".toml"])
def test_deeply_nested_scene_files_are_refused_without_a_traceback(tmp_path: Path, suffix: str):
    p = tmp_path / f"deep{suffix}"
    deep = "[" * 100_000 + "]" * 100_000
    p.write_text(deep if suffix == ".json" else f"x = {deep}\n")
    assert _field_within(lambda: SceneSpec.load(p)) == "scene"
    # brackets inside strings and comments do not count; a nesting at the limit passes
    check_nesting('{"a": "[[[[[[\\" [[[", "b": [[1]]}', "f", max_depth=3)
    check_nesting("a = \"[[[[[[\" # [[[[[[\nb = '[[[['\nc = [[1]]\n", "f", max_depth=3, toml=True)
    check_nesting("[" * MAX_NESTING + "]" * MAX_NESTING, "f")
    with pytest.raises(InvalidInputError):
        check_nesting("[" * (MAX_NESTING + 1) + "]" * (MAX_NESTING + 1), "f")


def _depth_by_hand(raw: bytes) -> int:
    """The nesting of ``raw`` read one byte at a time (the reference for the vectorised scan). A quote after an odd
    run of backslashes is escaped; outside strings that text is no JSON (the parser stops there), and the scan reads
    it the same way, so the reference does too."""
    depth = deepest = run = 0
    in_string = False
    for ch in raw:
        if ch == ord('"') and run % 2 == 0:
            in_string = not in_string
        elif not in_string and ch in b"[{":
            depth += 1
            deepest = max(deepest, depth)
        elif not in_string and ch in b"]}":
            depth -= 1
        run = run + 1 if ch == ord("\\") else 0
    return deepest


@pytest.mark.parametrize("chunk", [1, 2, 3, 7, 64, 1 << 18])
def test_json_depth_scans_chunks_as_one_text(monkeypatch, chunk: int):
    """The nesting scan works on chunks; strings, escapes and brackets that straddle a chunk's end are read as in
    one pass over the whole text (against a byte-at-a-time reading, on random texts of brackets, quotes, backslashes)."""
    monkeypatch.setattr(files, "_DEPTH_CHUNK", chunk)
    monkeypatch.setattr(files, "_CHUNK_INDEX", np.arange(chunk, dtype=np.int32))
    rng = np.random.default_rng(7)
    alphabet = np.frombuffer(b'[]{}"\\ a', np.uint8)
    for n in [0, 1, 2, 5, 40, 300] * 60:
        raw = rng.choice(alphabet, n).tobytes()
        assert files.json_depth(raw) == _depth_by_hand(raw), raw


def test_a_deeply_nested_json_sketch_is_refused():
    with pytest.raises(InvalidInputError) as e:
        Sketch.from_json("[" * 100_000 + "]" * 100_000)
    assert e.value.field == "sketch"


def test_an_unrepresentable_block_velocity_names_the_block_without_a_warning(tmp_path: Path):
    d = {"name": "fast", "dim": 2, "blocks": [{"material": "water", "lo": [0.2, 0.2], "hi": [0.4, 0.4], "velocity": [1e308, 0.0]}]}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InvalidInputError) as e:
            SceneSpec.from_dict(d)
    assert e.value.field == "blocks[0].velocity"


def _blocks(lo: np.ndarray, size: np.ndarray) -> list[dict]:
    return [{"material": "water" if i % 2 else "sand", "lo": a.tolist(), "hi": (a + s).tolist()} for i, (a, s) in enumerate(zip(lo, size))]


def test_scene_building_drops_overlaps_as_the_brute_force_does():
    """Random overlapping blocks: the particles kept are exactly those of each block's lattice outside every
    earlier block (brute force over all earlier blocks)."""
    rng = np.random.default_rng(5)
    lo = rng.integers(13, 180, (60, 2)) / 256  # whole lattice spacings (1/256 m on 128²): no stretched lattice
    size = rng.integers(4, 64, (60, 2)) / 256
    spec = SceneSpec.from_dict({"name": "overlaps", "dim": 2, "blocks": _blocks(lo, size)})
    # blocks that would lose every particle are refused; drop them from the case first
    keep_blocks, placed = [], []
    s = spec.spacing
    for b in spec.blocks:
        from hybridmpm.scenes.core import lattice

        p = lattice(np.asarray(b.lo), np.asarray(b.hi), s)
        inside = np.zeros(len(p), bool)
        for plo, phi in placed:
            inside |= np.all((p >= plo) & (p < phi), axis=1)
        if not inside.all():
            keep_blocks.append(b)
            placed.append((np.asarray(b.lo), np.asarray(b.hi)))
    spec = SceneSpec.from_dict({"name": "overlaps", "dim": 2, "blocks": [{"material": b.material, "lo": b.lo, "hi": b.hi} for b in keep_blocks]})
    scene = spec.build()
    want = []
    for i, b in enumerate(spec.blocks):
        p = lattice(np.asarray(b.lo), np.asarray(b.hi), s)
        inside = np.zeros(len(p), bool)
        for e in spec.blocks[:i]:
            inside |= np.all((p >= np.asarray(e.lo)) & (p < np.asarray(e.hi)), axis=1)
        want.append(p[~inside])
    assert np.array_equal(scene.positions, np.concatenate(want).astype(np.float32))


def test_many_blocks_build_fast_and_too_many_are_refused(tmp_path: Path):
    k = 64  # 4096 one-particle blocks on a 64 x 64 lattice of places (quadratic building took about two minutes)
    i = np.arange(k * k)
    lo = np.stack([0.05 + (i % k) * 0.85 / k, 0.05 + (i // k) * 0.85 / k], 1)
    spec = SceneSpec.from_dict({"name": "many", "dim": 2, "blocks": _blocks(lo, np.full_like(lo, 1 / 256))})
    t0 = time.perf_counter()
    assert spec.build().num_particles == k * k == MAX_BLOCKS
    assert time.perf_counter() - t0 < 30.0
    p = tmp_path / "too_many.json"
    n = 100_000
    i = np.arange(n)
    lo = np.stack([0.05 + (i % 317) * 0.85 / 317, 0.05 + (i // 317) * 0.85 / 317], 1)
    p.write_text(json.dumps({"name": "many", "dim": 2, "blocks": _blocks(lo, np.full_like(lo, 1 / 512))}))
    assert _field_within(lambda: SceneSpec.load(p), 10.0) == "blocks"


def _store_with(tmp_path: Path, make) -> tuple:
    pytest.importorskip("fastapi")
    from hybridmpm.service.store import SessionStore

    store = SessionStore(str(tmp_path / "store")).open()
    key = "a" * 64  # a SHA-256 hex name, as session_key makes
    make(Path(store.root) / f"{key}.npz")
    return store, key


@pytest.mark.parametrize("kind", ["fifo", "zero", "sparse"])
def test_store_records_that_are_not_regular_or_too_large_are_refused_without_hanging(tmp_path: Path, kind: str):
    def make(p: Path) -> None:
        if kind == "fifo":
            os.mkfifo(p)
        elif kind == "zero":
            p.symlink_to("/dev/zero")
        else:
            with open(p, "wb") as f:
                f.truncate(3 << 30)

    store, key = _store_with(tmp_path, make)
    assert key in store.keys()
    assert _field_within(lambda: store.load(key, 32 << 20), 5.0) == "checkpoint"


def _lying_zip(declared: int) -> bytes:
    """A small npz whose central directory declares ``declared`` bytes for its member."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr("__tree__.npy", b"\x93NUMPY" + b"\0" * 64)
    data = bytearray(buf.getvalue())
    cd = data.rfind(b"PK\x01\x02")
    data[cd + 24 : cd + 28] = struct.pack("<I", 0xFFFFFFFF if declared >= 0xFFFFFFFF else declared)
    return bytes(data)


def test_a_checkpoint_declaring_more_than_the_cap_is_422_not_503():
    pytest.importorskip("fastapi")
    from fastapi.testclient import TestClient

    from hybridmpm.service import ServiceConfig, create_app
    from hybridmpm.service import checkpoint as ckpt

    data = _lying_zip(3 << 30)
    assert ckpt.decoded_nbytes(data) >= 3 << 30 and len(data) < 400
    app = create_app(ServiceConfig(allowed_hosts=("testserver",), memory_budget="100M"))
    with TestClient(app) as c:
        sid = c.post("/v1/sessions", json={"scene": "water2d", "solver": "mpm"}).json()["id"]
        r = c.put(f"/v1/sessions/{sid}/checkpoint", content=data)
        assert r.status_code == 422, r.text
        assert "checkpoint" in r.text
