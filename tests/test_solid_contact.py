"""A solid keeps together where it touches a wall, an obstacle or the water
pressing it there: read from the particles' positions (their shape off a rigid
motion, Kabsch's fit by scipy; the area of the cells they occupy; the gap to a
particle's nearest neighbour), not only from ``F``.

The case that failed: a jello cube pressed by ``paddle3d``'s surge against the
paddle kept a strain it could not lose (6.7 % of its side off a rigid motion
with the water calm) because the obstacle put its particles back onto the
surface from a quarter cell deep, a jump its ``F`` did not see. A solid's
particle now only loses its inward velocity there and goes back from
``SOLID_PROJECT_DEPTH_CELLS`` (docs/materials.md, Limits)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

import hybridmpm as hm
from hybridmpm import _core
from hybridmpm.scenes import make_scene
from hybridmpm.scenes.spec import SceneSpec


def _off_rigid(rest: np.ndarray, now: np.ndarray) -> np.ndarray:
    """Each particle's distance [m] from where the best rigid motion of ``rest`` puts it."""
    pad = [(0, 0), (0, 3 - rest.shape[1])]
    a, b = np.pad(rest - rest.mean(0), pad), np.pad(now - now.mean(0), pad)
    rot, _ = Rotation.align_vectors(b, a)
    return np.linalg.norm(rot.apply(a) - b, axis=1)


def _nearest_gap(p: np.ndarray) -> float:
    """The largest distance [m] from a particle to its nearest neighbour (a shed particle's grows)."""
    return float(cKDTree(p).query(p, k=2)[0][:, 1].max())


def _area(p: np.ndarray, h: float) -> float:
    """The area [m²] of the cells of side ``h`` the 2D particles ``p`` occupy, averaged over 16 grid offsets."""
    out = []
    for ox in range(4):
        for oy in range(4):
            q = np.floor(p / h + np.array([ox, oy]) / 4).astype(np.int64)
            out.append(len(np.unique(q, axis=0)) * h * h)
    return float(np.mean(out))


def test_a_jello_pressed_against_the_paddle_by_the_surge_gets_its_shape_back():
    # the benchmark's run (benchmarks/solid_contact.py): the palette's cube poured behind the paddle, read every 20 frames
    rows = _load_solid_contact().run("jello", {}, 1000, 20)
    params = make_scene("paddle3d").params
    paddle = params.colliders[0]
    # the surge carried it to the paddle and left it there (its back face at x = 0.53 m)
    assert rows[-1]["x_min"] < paddle.center[0] + paddle.half_extents[0] + 0.5 / params.n_grid
    # no particle left the body: the nearest neighbour of each stayed within 1.2 spacings
    assert max(r["gap"] for r in rows) < 1.2
    # none deeper in the paddle than a solid may go before it is put back (a small margin for the last substep's step)
    assert rows[-1]["deepest"] <= _core.SOLID_PROJECT_DEPTH_CELLS + 0.02, rows[-1]["deepest"]
    # 2.5 s after the drop, the water slow, its shape is back within 3 % of its side (RMS, off a rigid motion; 3.3 % when its
    # particles went back from half a cell, 6.7 % from a quarter)
    assert rows[-1]["rms"] < 0.03, rows[-1]


def _load_solid_contact():
    spec = importlib.util.spec_from_file_location("solid_contact_script", Path(__file__).resolve().parents[1] / "benchmarks" / "solid_contact.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _jelly_block(lo: list[float], side: float, **scene: object) -> hm.Scene:
    d = {
        "dim": 2,
        "n_grid": 128,
        "walls": {"condition": "separate", "friction": 0.0},
        "blocks": [{"material": "elastic", "E": 1e6, "nu": 0.3, "density": 1000.0, "lo": lo, "hi": [lo[0] + side, lo[1] + side]}],
        **scene,
    }
    return SceneSpec.from_dict(d).build()


def test_a_jelly_dropped_onto_the_floor_keeps_its_area_and_its_shape():
    side = 0.2
    scene = _jelly_block([0.4, 0.30], side)
    traj = hm.rollout(hm.make_simulator(scene, "mpm"), 600)
    p = traj.positions[:, traj.material == 2].astype(np.float64)
    dx = 1.0 / 128
    floor = 3 * dx
    assert p[:, :, 1].min() < floor + dx  # it reached the floor (and bounces: the solid has no damping)
    a0 = _area(p[0], dx)
    for frame in range(0, 600, 25):
        area = _area(p[frame], dx) / a0
        off = _off_rigid(p[0], p[frame]) / side
        assert abs(area - 1) < 0.03, (frame, area)
        assert np.sqrt(np.mean(off**2)) < 0.02 and off.max() < 0.05, (frame, off)


def test_a_jelly_pressed_against_an_obstacle_deforms_as_against_a_wall():
    """Pushed by a sideways gravity against the x- wall or the face of a box obstacle at the same distance from
    the block, the jelly moves the same way: an obstacle's face holds a solid as a wall's does, flat."""
    side, dx = 0.12, 1.0 / 128
    runs = {}
    for against in ("wall", "box"):
        x0 = 3 * dx if against == "wall" else 0.5
        extra = {"gravity": [-9.8, 0.0]}
        if against == "box":
            extra["obstacles"] = [{"shape": "box", "center": [0.45, 0.5], "half_extents": [0.05, 0.3]}]
        scene = _jelly_block([x0 + 0.25 * dx, 0.4], side, **extra)
        traj = hm.rollout(hm.make_simulator(scene, "mpm"), 300)
        p = traj.positions[:, traj.material == 2].astype(np.float64)
        runs[against] = p - np.array([x0, 0.0])
    wall, box = runs["wall"], runs["box"]
    assert np.abs(wall - box).max() < 0.05 * dx, np.abs(wall - box).max()
    # the contact face stays flat and where the wall is: the first column's particles within a quarter cell of it
    first = wall[0, :, 0] < wall[0, :, 0].min() + 0.5 * dx
    assert wall[100:, first, 0].std(axis=1).max() < 0.3 * dx
    assert wall[100:, :, 0].min() > -0.25 * dx


def test_a_stiff_jelly_dropped_onto_a_crate_keeps_its_shape_and_stays_on_it():
    """A rigid body holds a solid through the grid (no particle is moved): the jelly lands on a heavy crate resting
    on the floor, bounces, and keeps its shape within 1 % of its side, none of its particles inside the crate."""
    side, dx = 0.12, 1.0 / 128
    top = 3 * dx + 0.102  # the crate's upper face [m]
    scene = _jelly_block([0.44, 0.30], side, bodies=[{"shape": "box", "center": [0.5, top - 0.05], "half_extents": [0.15, 0.05], "density": 3000.0}])
    traj = hm.rollout(hm.make_simulator(scene, "mpm"), 400)
    p = traj.positions[:, traj.material == 2].astype(np.float64)
    lowest = p[:, :, 1].min(axis=1)
    assert lowest.min() < top + 2 * dx  # it reached the crate
    assert lowest.min() > top - 0.5 * dx, (top - lowest.min()) / dx
    spacing = float(cKDTree(p[0]).query(p[0], k=2)[0][:, 1].max())
    for frame in range(0, 400, 20):
        off = _off_rigid(p[0], p[frame]) / side
        assert np.sqrt(np.mean(off**2)) < 0.01, (frame, off)
        assert _nearest_gap(p[frame]) < 1.1 * spacing
