"""hybridmpm._core.radius_graph against a numpy brute force and scipy's cKDTree."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from scipy.spatial import cKDTree

from hybridmpm import _core
from hybridmpm.errors import InvalidInputError

radius_graph = _core.radius_graph


def brute(pos: np.ndarray, r: float, self_edges: bool = True, k: int | None = None):
    """O(N^2) reference with the documented float32 criterion and ordering."""
    pos = np.asarray(pos, np.float32)
    n, dim = pos.shape
    d = pos[None, :, :] - pos[:, None, :]  # d[i, j] = p[j] - p[i]  (receiver i, sender j)
    dd = d[..., 0] * d[..., 0]
    for c in range(1, dim):
        dd = dd + d[..., c] * d[..., c]  # left to right, float32
    r32 = np.float32(r)
    mask = dd <= r32 * r32
    if not self_edges:
        np.fill_diagonal(mask, False)
    recv, send = np.nonzero(mask)  # row-major: by receiver, then sender
    if k is not None:
        dist = np.sqrt(dd[recv, send])
        keep = np.zeros(len(recv), bool)
        starts = np.searchsorted(recv, np.arange(n + 1))
        for i in range(n):
            a, b = starts[i], starts[i + 1]
            order = np.lexsort((send[a:b], dist[a:b]))  # by distance, then index
            keep[a + order[:k]] = True
        recv, send = recv[keep], send[keep]
    disp = pos[send] - pos[recv]
    dist = np.sqrt(dd[recv, send])
    return send.astype(np.int64), recv.astype(np.int64), disp, dist


def assert_same(got, want):
    s, r, dp, ds = got
    ws, wr, wdp, wds = want
    assert s.dtype == np.int64 and r.dtype == np.int64
    assert dp.dtype == np.float32 and ds.dtype == np.float32
    assert dp.shape == wdp.shape and ds.shape == wds.shape
    np.testing.assert_array_equal(r, wr)
    np.testing.assert_array_equal(s, ws)
    np.testing.assert_array_equal(dp, wdp)
    np.testing.assert_allclose(ds, wds, rtol=1e-6, atol=0)


def check_sorted(s, r):
    key = r * (max(int(s.max(initial=0)), int(r.max(initial=0))) + 1) + s
    assert np.all(np.diff(key) > 0), "edges not sorted by (receiver, sender)"


def cloud(seed: int, n: int, dim: int):
    rng = np.random.default_rng(seed)
    off = rng.uniform(-100, 100, dim)
    size = rng.uniform(0.05, 5.0)
    return (off + size * rng.random((n, dim))).astype(np.float32), size


@settings(max_examples=80, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(0, 250),
    dim=st.sampled_from([2, 3]),
    frac=st.floats(0.005, 0.6),
    self_edges=st.booleans(),
)
def test_matches_brute_force(seed, n, dim, frac, self_edges):
    pos, size = cloud(seed, n, dim)
    r = frac * size
    got = radius_graph(pos, r, self_edges=self_edges)
    assert_same(got, brute(pos, r, self_edges))
    check_sorted(got[0], got[1])


@settings(max_examples=60, deadline=None)
@given(
    pos=st.integers(0, 150).flatmap(
        lambda n: st.sampled_from([2, 3]).flatmap(
            lambda dim: hnp.arrays(
                np.float32,
                (n, dim),
                # Small integers: duplicates and exact distance ties.
                elements=st.integers(-3, 3).map(float),
            )
        )
    ),
    r=st.sampled_from([0.5, 1.0, 1.5, 2.0, 3.0]),
    self_edges=st.booleans(),
    k=st.one_of(st.none(), st.integers(1, 10)),
)
def test_lattice_ties_and_cap(pos, r, self_edges, k):
    got = radius_graph(pos, r, self_edges=self_edges, max_neighbors=k)
    assert_same(got, brute(pos, r, self_edges, k))


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 250),
    dim=st.sampled_from([2, 3]),
    frac=st.floats(0.05, 0.5),
    k=st.integers(1, 20),
    self_edges=st.booleans(),
)
def test_cap_keeps_k_nearest(seed, n, dim, frac, k, self_edges):
    pos, size = cloud(seed, n, dim)
    r = frac * size
    got = radius_graph(pos, r, self_edges=self_edges, max_neighbors=k)
    assert_same(got, brute(pos, r, self_edges, k))
    full = radius_graph(pos, r, self_edges=self_edges)
    counts = np.bincount(got[1], minlength=n)
    full_counts = np.bincount(full[1], minlength=n)
    np.testing.assert_array_equal(counts, np.minimum(full_counts, k))
    # Every kept edge is no longer than any dropped edge of its receiver.
    for i in np.flatnonzero(full_counts > k)[:20]:
        kept = got[3][got[1] == i]
        all_d = np.sort(full[3][full[1] == i])
        assert kept.max() <= all_d[k - 1]


def kdtree_edges(pos: np.ndarray, r: float, self_edges: bool):
    """Directed edge set from scipy (float64 arithmetic), sorted like ours."""
    n = len(pos)
    pairs = cKDTree(pos.astype(np.float64)).query_pairs(r, output_type="ndarray")
    s = np.concatenate([pairs[:, 0], pairs[:, 1]])
    rv = np.concatenate([pairs[:, 1], pairs[:, 0]])
    if self_edges:
        s = np.concatenate([s, np.arange(n)])
        rv = np.concatenate([rv, np.arange(n)])
    order = np.lexsort((s, rv))
    return s[order].astype(np.int64), rv[order].astype(np.int64)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(0, 2000),
    dim=st.sampled_from([2, 3]),
    frac=st.floats(0.01, 0.3),
    self_edges=st.booleans(),
)
def test_matches_ckdtree(seed, n, dim, frac, self_edges):
    pos, size = cloud(seed, n, dim)
    r = float(np.float32(frac * size))
    s, rv, disp, dist = radius_graph(pos, r, self_edges=self_edges)
    ks, kr = kdtree_edges(pos, r, self_edges)
    ours = set(zip(rv.tolist(), s.tolist()))
    theirs = set(zip(kr.tolist(), ks.tolist()))
    # float32 vs float64 arithmetic may only disagree right at the radius.
    p64 = pos.astype(np.float64)
    for i, j in ours ^ theirs:
        assert abs(np.linalg.norm(p64[j] - p64[i]) - r) <= 1e-5 * r, (i, j)
    if ours == theirs:
        np.testing.assert_array_equal(s, ks)
        np.testing.assert_array_equal(rv, kr)
    check_sorted(s, rv)
    # Features, checked in float64.
    want = p64[s] - p64[rv]
    np.testing.assert_allclose(disp, want, rtol=0, atol=1e-6 * (np.abs(p64).max(initial=1) + 1))
    np.testing.assert_allclose(dist, np.linalg.norm(disp.astype(np.float64), axis=1), rtol=1e-6)
    assert np.all(dist <= np.float32(r) * (1 + 1e-6))


def test_default_radius_and_self_edges():
    pos = np.array([[0.0, 0.0], [0.01, 0.0], [0.03, 0.0]], np.float32)
    s, r, disp, dist = radius_graph(pos)  # R = 0.015, self edges on
    assert list(zip(r.tolist(), s.tolist())) == [(0, 0), (0, 1), (1, 0), (1, 1), (2, 2)]
    np.testing.assert_array_equal(disp[1], pos[1] - pos[0])  # sender - receiver
    assert dist[1] == np.float32(0.01)
    s, r, _, _ = radius_graph(pos, self_edges=False)
    assert list(zip(r.tolist(), s.tolist())) == [(0, 1), (1, 0)]


def test_far_outlier():
    g = np.stack(np.meshgrid(np.arange(40), np.arange(40), indexing="ij"), -1).reshape(-1, 2)
    pos = (g * 0.005).astype(np.float32)
    pos = np.concatenate([pos, np.array([[1e6, -1e6]], np.float32)])
    got = radius_graph(pos, 0.015)
    assert_same(got, brute(pos, 0.015))
    assert got[0][-1] == len(pos) - 1 and got[1][-1] == len(pos) - 1


def test_non_contiguous_and_empty():
    rng = np.random.default_rng(0)
    base = rng.random((300, 6)).astype(np.float32)
    for pos in (base[::2, 1:4], base[:, ::-2], np.asfortranarray(base[:, :3])):
        assert not pos.flags.c_contiguous
        got = radius_graph(pos, 0.2)
        assert_same(got, brute(np.ascontiguousarray(pos), 0.2))
    for dim in (2, 3):
        s, r, disp, dist = radius_graph(np.zeros((0, dim), np.float32))
        assert s.shape == r.shape == dist.shape == (0,) and disp.shape == (0, dim)
        assert s.dtype == np.int64 and disp.dtype == np.float32


def test_thread_count_does_not_change_output(tmp_path):
    code = (
        "import numpy as np, hashlib\n"
        "from hybridmpm import _core\n"
        "p = np.random.default_rng(1).random((20000, 3)).astype(np.float32)\n"
        "out = _core.radius_graph(p, 0.04, max_neighbors=30)\n"
        "print(hashlib.sha256(b''.join(a.tobytes() for a in out)).hexdigest(), len(out[0]))\n"
    )
    outs = []
    for t in ("1", "2"):
        env = dict(os.environ, RAYON_NUM_THREADS=t)
        res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
        outs.append(res.stdout.split())
    assert int(outs[0][1]) > 20000
    assert outs[0] == outs[1]


GOOD = np.zeros((4, 2), np.float32)


@pytest.mark.parametrize(
    ("args", "kwargs", "field"),
    [
        ((GOOD.astype(np.float64),), {}, "positions"),
        ((GOOD.astype(np.float16),), {}, "positions"),
        ((GOOD.tolist(),), {}, "positions"),
        ((np.zeros(4, np.float32),), {}, "positions"),
        ((np.zeros((2, 2, 2), np.float32),), {}, "positions"),
        ((np.zeros((4, 4), np.float32),), {}, "positions"),
        ((np.zeros((4, 1), np.float32),), {}, "positions"),
        ((np.array([[0, 0], [np.nan, 1]], np.float32),), {}, "positions"),
        ((np.array([[0, 0, 0], [0, np.inf, 1]], np.float32),), {}, "positions"),
        ((GOOD, 0.0), {}, "radius"),
        ((GOOD, -0.1), {}, "radius"),
        ((GOOD, float("nan")), {}, "radius"),
        ((GOOD, float("inf")), {}, "radius"),
        ((GOOD, 1e300), {}, "radius"),
        ((GOOD, 1e-60), {}, "radius"),
        ((GOOD,), {"max_neighbors": 0}, "max_neighbors"),
        ((GOOD,), {"max_neighbors": -3}, "max_neighbors"),
        ((GOOD,), {"max_edges": -1}, "max_edges"),
        ((GOOD,), {"max_edges": True}, "max_edges"),
        ((GOOD,), {"max_edges": 2.5}, "max_edges"),
        ((GOOD, 1.0), {"max_edges": 15}, "radius"),  # 4 coincident points: 16 edges
    ],
)
def test_invalid_input(args, kwargs, field):
    with pytest.raises(InvalidInputError) as info:
        radius_graph(*args, **kwargs)
    assert isinstance(info.value, ValueError)
    assert info.value.field == field
    assert field in str(info.value)


def test_nan_message_names_index():
    pos = np.zeros((5, 3), np.float32)
    pos[3, 2] = np.nan
    with pytest.raises(ValueError, match=r"positions.*\[3\]"):
        radius_graph(pos, 0.1)


def _graph_in_child(x, q):
    from hybridmpm.graph import radius_graph as rg

    s, r, _, _ = rg(x, 0.02)
    q.put(len(s))


def test_radius_graph_in_a_forked_child():
    """The parallel path (≥ 8192 particles) works in a child forked after the
    parent used it (rayon's global pool would not survive the fork)."""
    import multiprocessing as mp

    from hybridmpm.graph import radius_graph as rg

    x = np.random.default_rng(0).uniform(0, 1, (20000, 3)).astype(np.float32)
    n_parent = len(rg(x, 0.02)[0])
    ctx = mp.get_context("fork")
    q = ctx.Queue()
    p = ctx.Process(target=_graph_in_child, args=(x, q))
    p.start()
    p.join(timeout=60)
    assert p.exitcode == 0, "child hung or crashed"
    assert q.get(timeout=5) == n_parent
