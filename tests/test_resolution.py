"""Spatial and temporal downsampling (paper Sec. 3.1.1): clustering conserves
mass, centre of mass and momentum; r_p = 1 is the identity."""

from __future__ import annotations

import numpy as np
import pytest

from hybridmpm.errors import InvalidInputError
from hybridmpm.scenes import make_scene
from hybridmpm.scenes.resolution import (
    PAPER_R_P,
    cluster_centroids,
    cluster_particles,
    downsample_scene,
    temporal_downsample,
)


@pytest.mark.parametrize(("name", "seed"), [("water_sand2d", 1), ("water3d", 2), ("sand_ramps2d", 3)])
def test_clustering_conserves_mass_centre_of_mass_and_momentum(name, seed):
    scene = make_scene(name, seed)
    sim = scene.make_solver(num_threads=1)
    m = sim.masses.astype(np.float64)
    down = downsample_scene(scene, PAPER_R_P, seed=seed)
    low = down.scene
    ml = low.masses.astype(np.float64)
    # N_l = r_p·N_h per material (rounded)
    for mat in (0, 1):
        n_h = int((scene.material == mat).sum())
        assert int((low.material == mat).sum()) == (max(1, round(PAPER_R_P * n_h)) if n_h else 0)
        # mass per material conserved (float32 storage of the cluster masses)
        assert np.isclose(ml[low.material == mat].sum(), m[scene.material == mat].sum(), rtol=1e-6)
    # a cluster never mixes materials
    assert np.array_equal(low.material[down.labels], scene.material)
    com_h = (m[:, None] * scene.positions).sum(0) / m.sum()
    com_l = (ml[:, None] * low.positions).sum(0) / ml.sum()
    assert np.allclose(com_h, com_l, atol=1e-6)
    assert np.allclose((m[:, None] * scene.velocities).sum(0), (ml[:, None] * low.velocities).sum(0), rtol=1e-5, atol=1e-5)
    assert np.isclose(low.volumes.sum(), sim.volumes.astype(np.float64).sum(), rtol=1e-6)
    # every cluster sits at its members' centroid, within the block
    for k in range(0, len(ml), max(1, len(ml) // 50)):
        members = scene.positions[down.labels == k]
        assert np.allclose(low.positions[k], members.mean(0), atol=1e-6)  # equal masses within a material here
    if scene.num_boundary:
        assert 0 < low.num_boundary < scene.num_boundary
    # the low-resolution scene runs
    s = low.make_solver(num_threads=1)
    s.step_frame()
    assert np.isfinite(s.positions).all()


def test_r_p_one_is_the_identity():
    scene = make_scene("water_ramps2d", 0)
    down = downsample_scene(scene, 1.0)
    assert down.scene is scene
    assert np.array_equal(down.labels, np.arange(scene.num_particles))
    x = scene.positions
    assert np.array_equal(cluster_particles(x, 1.0), np.arange(len(x)))
    assert np.array_equal(cluster_centroids(x, np.arange(len(x))), x)


def test_labels_are_deterministic_and_grouped():
    x = np.random.default_rng(0).uniform(0.2, 0.8, (600, 2))
    g = (x[:, 0] > 0.5).astype(int)
    a = cluster_particles(x, 0.5, groups=g, seed=4)
    b = cluster_particles(x, 0.5, groups=g, seed=4)
    assert np.array_equal(a, b)
    assert len(np.unique(a)) == round(0.5 * (g == 0).sum()) + round(0.5 * (g == 1).sum())
    for k in np.unique(a):
        assert len(np.unique(g[a == k])) == 1
    # labels are compact: 0..N_l-1
    assert np.array_equal(np.unique(a), np.arange(a.max() + 1))


def test_centroids_follow_a_trajectory():
    rng = np.random.default_rng(1)
    traj = rng.uniform(0, 1, (5, 40, 3)).astype(np.float32)
    labels = np.repeat(np.arange(20), 2)
    m = rng.uniform(1, 2, 40)
    c = cluster_centroids(traj, labels, m)
    assert c.shape == (5, 20, 3)
    want = (traj[:, 0::2] * m[0::2, None] + traj[:, 1::2] * m[1::2, None]) / (m[0::2] + m[1::2])[:, None]
    assert np.allclose(c, want, atol=1e-6)


def test_temporal_downsampling_keeps_every_r_t_th_frame():
    x = np.arange(11)[:, None, None] * np.ones((1, 3, 2))
    assert np.array_equal(temporal_downsample(x, 2)[:, 0, 0], [0, 2, 4, 6, 8, 10])
    assert temporal_downsample(x, 1) is not None and len(temporal_downsample(x, 1)) == 11


@pytest.mark.parametrize("r_p", [0.0, -0.5, 1.5, float("nan"), "half"])
def test_bad_r_p(r_p):
    with pytest.raises(InvalidInputError) as e:
        cluster_particles(np.zeros((4, 2)), r_p)
    assert e.value.field == "r_p"


def test_bad_r_t_and_positions():
    with pytest.raises(InvalidInputError) as e:
        temporal_downsample(np.zeros((3, 2, 2)), 0)
    assert e.value.field == "r_t"
    with pytest.raises(InvalidInputError) as e:
        cluster_particles(np.full((4, 2), np.nan), 0.5)
    assert e.value.field == "positions"


@pytest.mark.parametrize(("name", "seed"), [("water_sand2d", 4), ("water_ramps2d", 5)])
def test_clusters_rebuild_the_same_scene_without_clustering(name, seed):
    scene = make_scene(name, seed)
    first = downsample_scene(scene, PAPER_R_P, seed=seed).scene
    assert first.clusters is not None
    # labels that differ from what k-means would give (another seed): the scene follows the labels given
    other = downsample_scene(scene, PAPER_R_P, seed=seed + 100).scene
    again = downsample_scene(scene, PAPER_R_P, seed=seed + 100, clusters=first.clusters).scene
    for field in ("positions", "velocities", "material", "masses", "volumes", "boundary_positions"):
        assert np.array_equal(getattr(again, field), getattr(first, field)), field
    assert not np.array_equal(other.positions, first.positions)  # the rebuild did not cluster again
    assert np.array_equal(again.clusters.labels, first.clusters.labels)


def test_bad_clusters_are_refused_naming_the_field():
    from hybridmpm.scenes import Clusters

    scene = make_scene("water_sand2d", 6)
    good = downsample_scene(scene, PAPER_R_P, seed=6).scene.clusters
    bad = {
        "clusters.labels": [
            Clusters(good.labels[:-1], good.boundary_labels),  # wrong length
            Clusters(good.labels.astype(np.float32), good.boundary_labels),  # not integers
            Clusters(np.zeros_like(good.labels), good.boundary_labels),  # too few clusters, mixing materials
            Clusters(np.where(good.labels == 0, good.labels.max() + 1, good.labels), good.boundary_labels),  # a gap in the numbering
        ],
    }
    # swap one water and one sand particle's labels: the counts still fit, the materials mix
    water, sand = np.flatnonzero(scene.material == 0)[0], np.flatnonzero(scene.material == 1)[0]
    mixed = good.labels.copy()
    mixed[[water, sand]] = mixed[[sand, water]]
    bad["clusters.labels"].append(Clusters(mixed, good.boundary_labels))
    for field, cases in bad.items():
        for c in cases:
            with pytest.raises(InvalidInputError) as e:
                downsample_scene(scene, PAPER_R_P, seed=6, clusters=c)
            assert e.value.field == field
