"""Fluid surfaces of water spread thin and resting on walls (docs/mesh.md):
films thinner than a cell keep their volume, every body of water gets its
own level, and the closure against walls and obstacles leaves no duplicate
or zero-area face."""

from __future__ import annotations

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")

from hybridmpm.conventions import GNS_WATER  # noqa: E402
from hybridmpm.mpm import Box, Sphere  # noqa: E402
from hybridmpm.render.surface import surface_mesh, surface_settings  # noqa: E402
from hybridmpm.scenes import collider_sdf, make_scene  # noqa: E402
from hybridmpm.scenes.core import lattice  # noqa: E402
from hybridmpm.sim import MpmSimulator, rollout  # noqa: E402

N_GRID = 32
DX = 1.0 / N_GRID
FACE = 2 * DX  # the wall face of a 32-cell grid with a 3-cell wall band
DOMAIN3 = ([FACE] * 3, [1 - FACE] * 3)
V_P = (DX / 2) ** 3  # the default particle volume: the scenes' lattice


def film(spacing: float, cells: int = 16, x0: float = 4, z0: float = 6) -> np.ndarray:
    """One layer of particles on the floor, ``spacing`` cells apart (a film
    ``(1/2)³ / spacing²`` cells thick at rest density), lying within a quarter
    cell of the wall face as an MPM run leaves them, jittered."""
    g = np.arange(0, cells, spacing) + spacing / 2
    x, z = np.meshgrid(FACE + (x0 + g) * DX, FACE + (z0 + g) * DX, indexing="ij")
    p = np.stack([x.ravel(), np.full(x.size, FACE), z.ravel()], axis=1)
    rng = np.random.default_rng(0)
    p[:, [0, 2]] += rng.uniform(-0.1, 0.1, (len(p), 2)) * spacing * DX
    p[:, 1] += rng.uniform(0, 0.25, len(p)) * DX
    return p


def check_clean(vertices: np.ndarray, faces: np.ndarray) -> trimesh.Trimesh:
    """Closed, consistently wound outwards, and no face twice (by the
    positions of its vertices, either orientation) or of zero area."""
    tm = trimesh.Trimesh(vertices, faces, process=False)
    assert len(faces) and tm.is_watertight and tm.is_winding_consistent and tm.volume > 0
    _, at = np.unique(vertices, axis=0, return_inverse=True)
    by_position = np.sort(at.ravel()[faces], axis=1)
    assert (by_position[:, 0] < by_position[:, 1]).all() and (by_position[:, 1] < by_position[:, 2]).all(), "a face with two vertices in one place"
    assert len(np.unique(by_position, axis=0)) == len(faces), "a face twice"
    assert tm.area_faces.min() > 1e-12 * DX**2, "a zero-area face"
    return tm


@pytest.mark.parametrize("spacing", [0.5, 0.75, 1.0])
def test_a_film_thinner_than_a_cell_keeps_its_volume_beside_a_falling_block(spacing):
    sheet = film(spacing)
    lo, hi = np.array([FACE + 20 * DX, 0.5, FACE + 20 * DX]), np.array([FACE + 26 * DX, 0.5 + 6 * DX, FACE + 26 * DX])
    p = np.concatenate([sheet, lattice(lo, hi, DX / 2).astype(np.float64)])
    (mesh,) = surface_mesh(p, np.full(len(p), GNS_WATER), domain=DOMAIN3, dx=DX)
    tm = check_clean(mesh.vertices, mesh.faces)
    assert abs(tm.volume / (len(p) * V_P) - 1) < 0.05
    parts = tm.split(only_watertight=True)
    on_floor = [m for m in parts if m.vertices[:, 1].max() < FACE + 2 * DX]
    in_air = [m for m in parts if m.vertices[:, 1].min() > 0.4]
    assert len(on_floor) + len(in_air) == len(parts) and len(in_air) == 1
    # each body holds its own particles' volume: the film its film's, the block its block's
    assert abs(sum(m.volume for m in on_floor) / (len(sheet) * V_P) - 1) < 0.05
    assert abs(in_air[0].volume / np.prod(hi - lo) - 1) < 0.05
    # the film lies on the floor and is thinner than a cell
    floor = np.concatenate([m.vertices for m in on_floor])
    assert abs(floor[:, 1].min() - FACE) < 1e-9 and floor[:, 1].max() < FACE + DX


def _block_in_a_layer() -> np.ndarray:
    """An 8-cell block resting on the floor in a layer of water a third of a cell thick."""
    layer = film(0.4, cells=24, x0=2, z0=2)
    inside = ((layer[:, [0, 2]] > FACE + 9.5 * DX) & (layer[:, [0, 2]] < FACE + 18.5 * DX)).all(axis=1)
    block = lattice([FACE + 10 * DX, FACE, FACE + 10 * DX], [FACE + 18 * DX, FACE + 8 * DX, FACE + 18 * DX], DX / 2)
    return np.concatenate([layer[~inside], block.astype(np.float64)])


def _on_shelf_and_ball() -> tuple[np.ndarray, list]:
    """A block on a box whose top face lies on a node layer, a ball pressed into its side."""
    shelf = Box(center=[0.4, 11 * DX - 0.05, 0.4], half_extents=[0.2, 0.05, 0.2])
    ball = Sphere(center=[0.625, 0.45, 0.4], radius=2 * DX)
    p = lattice([0.25, 11 * DX, 0.25], [0.55, 11 * DX + 0.2, 0.55], DX / 2).astype(np.float64)
    return p[collider_sdf(ball, p) > DX / 4], [shelf, ball]


@pytest.mark.parametrize("iso", ["volume", 0.3, 0.35, 0.5])
@pytest.mark.parametrize("case", ["block in a layer", "block in a corner", "on a shelf"])
def test_water_closed_against_walls_and_obstacles_has_no_duplicate_or_zero_area_face(case, iso):
    # 0.3 is rounded up in float32 (what marching cubes compares in), 0.35 down, 0.5 exactly
    obstacles: list = []
    if case == "block in a layer":
        p = _block_in_a_layer()
    elif case == "block in a corner":
        p = lattice([FACE] * 3, [FACE + 12 * DX, FACE + 10 * DX, FACE + 14 * DX], DX / 2).astype(np.float64)
    else:
        p, obstacles = _on_shelf_and_ball()
    (mesh,) = surface_mesh(p, np.full(len(p), GNS_WATER), domain=DOMAIN3, dx=DX, obstacles=obstacles, iso=iso)
    check_clean(mesh.vertices, mesh.faces)
    for ob in obstacles:
        assert collider_sdf(ob, mesh.vertices).min() > -0.05 * DX
    if case != "on a shelf":
        assert abs(mesh.vertices[:, 1].min() - FACE) < 1e-9  # on the floor


def test_water3d_spread_over_the_floor_keeps_its_volume():
    # water3d seed 1: from frame 57 on most of the water lies on the floor in a layer thinner than a cell
    scene = make_scene("water3d", seed=1)
    ro = rollout(MpmSimulator(scene, threads=1), 100)
    settings = surface_settings(scene.params, ro.particle_type, ro.masses)
    volume = float(settings["volumes"].sum())
    for t in range(56, 101, 4):
        (mesh,) = surface_mesh(ro.positions[t], ro.particle_type, **settings)
        check_clean(mesh.vertices, mesh.faces)
        assert abs(mesh.volume / volume - 1) < 0.05, t
