"""Spatial (``r_p``) and temporal (``r_t``) downsampling (paper Sec. 3.1.1).

Spatial downsampling merges the ``N_h`` particles of a scene into
``N_l = r_p·N_h`` particles by k-means clustering (scikit-learn), each material
(and the static boundary particles) clustered on its own so that a cluster
never mixes water and sand. A cluster particle sits at the mass-weighted
centroid of its members and carries their summed mass and rest volume and
their mass-weighted mean velocity, so total mass, centre of mass and momentum
are conserved exactly (up to float32 rounding of the stored positions).
Temporal downsampling keeps every ``r_t``-th frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from hybridmpm.conventions import MATERIAL_WATER, MATERIALS
from hybridmpm.errors import InvalidInputError
from hybridmpm.limits import check_seed
from hybridmpm.mpm.params import INTEGRATORS
from hybridmpm.scenes.core import Clusters, Scene

#: The paper's choice (Sec. 3.1.1, from its Fig. 5 ablation).
PAPER_R_P = 1 / 1.75
PAPER_R_T = 2


def check_r_p(r_p: float) -> float:
    """Validate ``r_p ∈ (0, 1]``; returns it as float. Raises :class:`InvalidInputError`."""
    if not (isinstance(r_p, (int, float)) and math.isfinite(r_p) and 0.0 < r_p <= 1.0):
        raise InvalidInputError(f"r_p: must be a number in (0, 1], got {r_p!r}", "r_p")
    return float(r_p)


def check_r_t(r_t: int) -> int:
    """Validate ``r_t`` (an integer ≥ 1). Raises :class:`InvalidInputError`."""
    if isinstance(r_t, bool) or not isinstance(r_t, (int, np.integer)) or r_t < 1:
        raise InvalidInputError(f"r_t: must be an integer >= 1, got {r_t!r}", "r_t")
    return int(r_t)


#: Seeds scikit-learn's k-means takes as its ``random_state``: [0, 2^32).
KMEANS_SEEDS = 2**32


def kmeans_seed(seed: int) -> int:
    """The k-means ``random_state`` of ``seed`` (an integer in [0, 2^63)): the seed itself below
    :data:`KMEANS_SEEDS` = 2^32 (so every such seed clusters as it always did), else one derived from it
    by numpy's ``SeedSequence``, in [0, 2^32) (the same seed always gives the same one). Raises
    :class:`InvalidInputError` (``seed``) for a seed outside [0, 2^63)."""
    seed = check_seed(seed)
    return seed if seed < KMEANS_SEEDS else int(np.random.SeedSequence(seed).generate_state(1, np.uint32)[0])


def cluster_particles(
    positions: np.ndarray,
    r_p: float,
    *,
    groups: np.ndarray | None = None,
    weights: np.ndarray | None = None,
    seed: int = 0,
) -> np.ndarray:
    """Cluster labels merging ``N`` particles into ``≈ r_p·N`` (paper Sec. 3.1.1).

    ``positions`` float [N, D] [m]; ``groups`` int [N] (particles of different
    groups never share a cluster; default one group); ``weights`` [N] (k-means
    sample weights, e.g. masses). Each group of ``n`` particles becomes
    ``max(1, round(r_p·n))`` clusters (k-means, one k-means++ start seeded by
    ``seed``, an integer in [0, 2^63) given to k-means through :func:`kmeans_seed`, run
    single-threaded so that labels do not depend on the machine).
    Returns int64 labels [N] in ``[0, N_l)``, numbered group by group (in
    ascending group value) then by the lowest member index. ``r_p = 1`` returns
    ``arange(N)`` (the identity) without clustering.
    Raises :class:`InvalidInputError` for a bad ``r_p``, ``seed`` or shapes.
    """
    r_p = check_r_p(r_p)
    random_state = kmeans_seed(seed)
    x = np.asarray(positions, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] not in (2, 3):
        raise InvalidInputError(f"positions: expected shape [N, 2|3], got {x.shape}", "positions")
    if not np.all(np.isfinite(x)):
        raise InvalidInputError("positions: contain NaN or inf", "positions")
    n = len(x)
    g = np.zeros(n, np.int64) if groups is None else np.asarray(groups).astype(np.int64)
    if g.shape != (n,):
        raise InvalidInputError(f"groups: expected shape [{n}], got {g.shape}", "groups")
    w = None if weights is None else np.asarray(weights, dtype=np.float64)
    if w is not None and (w.shape != (n,) or not np.all(w > 0)):
        raise InvalidInputError(f"weights: expected {n} positive numbers", "weights")
    if r_p == 1.0:
        return np.arange(n, dtype=np.int64)
    from sklearn.cluster import KMeans
    from threadpoolctl import threadpool_limits

    labels = np.empty(n, np.int64)
    offset = 0
    for value in np.unique(g):
        idx = np.flatnonzero(g == value)
        k = max(1, int(round(r_p * len(idx))))
        if k >= len(idx):
            local = np.arange(len(idx))
        else:
            with threadpool_limits(1):
                km = KMeans(n_clusters=k, n_init=1, random_state=random_state).fit(x[idx], sample_weight=None if w is None else w[idx])
            local = km.labels_.astype(np.int64)
        # renumber compactly by first appearance (drops any empty cluster)
        _, first, inv = np.unique(local, return_index=True, return_inverse=True)
        rank = np.empty(len(first), np.int64)
        rank[np.argsort(first, kind="stable")] = np.arange(len(first))
        labels[idx] = offset + rank[inv]
        offset += len(first)
    return labels


def cluster_sums(values: np.ndarray, labels: np.ndarray, n_clusters: int | None = None) -> np.ndarray:
    """Sum ``values`` [N, ...] over clusters: float64 [N_l, ...]."""
    labels = np.asarray(labels)
    k = int(labels.max()) + 1 if n_clusters is None else n_clusters
    v = np.asarray(values, dtype=np.float64)
    out = np.zeros((k,) + v.shape[1:], np.float64)
    np.add.at(out, labels, v)
    return out


def cluster_centroids(positions: np.ndarray, labels: np.ndarray, masses: np.ndarray | None = None) -> np.ndarray:
    """Mass-weighted centroids of clusters: positions [..., N, D] → float32 [..., N_l, D].

    Works on one frame [N, D] or a trajectory [T, N, D] (the members of a
    cluster are followed over time: the "centroid" low-resolution data).
    """
    x = np.asarray(positions, dtype=np.float64)
    labels = np.asarray(labels)
    k = int(labels.max()) + 1
    m = np.ones(x.shape[-2]) if masses is None else np.asarray(masses, np.float64)
    mt = cluster_sums(m, labels, k)
    moved = np.moveaxis(x * m[:, None], -2, 0)  # [N, ..., D]
    sums = cluster_sums(moved.reshape(moved.shape[0], -1), labels, k).reshape((k,) + moved.shape[1:])
    cent = np.moveaxis(sums, 0, -2) / mt[:, None]
    return cent.astype(np.float32)


@dataclass
class Downsampled:
    """Result of :func:`downsample_scene`: the low-resolution ``scene`` and the
    cluster ``labels`` [N_h] of the original solver particles (int64, values in
    ``[0, N_l)``) and ``boundary_labels`` [B_h] of its boundary particles."""

    scene: Scene
    labels: np.ndarray
    boundary_labels: np.ndarray


def check_clusters(clusters: Clusters, scene: Scene, r_p: float) -> Clusters:
    """Validate ``clusters`` as a clustering of ``scene`` at ``r_p``: integer
    labels of the right lengths ([N_h] and [B_h]), numbered ``0 .. N_l − 1``
    with no empty cluster, ``N_l`` the count :func:`cluster_particles` gives
    at ``r_p``, and no cluster mixing materials. Returns them as int64 arrays.
    Raises :class:`InvalidInputError` naming ``clusters.labels`` or
    ``clusters.boundary_labels``."""

    def one(name: str, values: np.ndarray, n: int, groups: np.ndarray) -> np.ndarray:
        a = np.asarray(values)
        if a.shape != (n,) or not np.issubdtype(a.dtype, np.integer):
            raise InvalidInputError(f"clusters.{name}: expected {n} integers, got {a.dtype} {a.shape}", f"clusters.{name}")
        a = a.astype(np.int64)
        want = sum(max(1, int(round(r_p * int(np.sum(groups == v))))) for v in np.unique(groups)) if n else 0
        if n and (a.min() != 0 or a.max() + 1 != want or len(np.unique(a)) != want):
            raise InvalidInputError(f"clusters.{name}: must number {want} non-empty clusters 0..{want - 1} (r_p = {r_p:g})", f"clusters.{name}")
        if n:
            first = np.full(want, -1, np.int64)
            first[a] = groups
            if np.any(first[a] != groups):
                raise InvalidInputError(f"clusters.{name}: a cluster mixes materials", f"clusters.{name}")
        return a

    labels = one("labels", clusters.labels, scene.num_particles, np.asarray(scene.material, np.int64))
    b_labels = one("boundary_labels", clusters.boundary_labels, scene.num_boundary, np.zeros(scene.num_boundary, np.int64))
    return Clusters(labels, b_labels)


def downsample_scene(scene: Scene, r_p: float, seed: int = 0, clusters: Clusters | None = None) -> Downsampled:
    """Merge a scene's particles into ``≈ r_p·N_h`` by clustering (paper Sec. 3.1.1).

    Materials are clustered separately; each cluster particle gets its members'
    summed mass [kg] and rest volume [m^D], their mass-weighted centroid and
    mean velocity (momentum conserved) and volume-weighted mean J. Boundary
    particles (static) are clustered with the same ``r_p``; a merged boundary
    particle belongs to the obstacle most of its members lie on (the lowest
    index on a tie; ``Scene.boundary_obstacle``). ``r_p = 1`` returns
    the scene unchanged (identity labels). ``clusters`` (the low-resolution
    scene's :attr:`~hybridmpm.scenes.Scene.clusters` from an earlier call
    with the same scene and ``r_p``) skips the k-means: the same scene comes
    back, about 3 s sooner in a fresh process (scikit-learn's import and the
    fit). The returned scene records its clusters. Raises
    :class:`InvalidInputError` (``r_p``, ``clusters.*``).
    """
    r_p = check_r_p(r_p)
    n = scene.num_particles
    sim = scene.make_solver(num_threads=1)  # resolves default masses/volumes exactly as the solver does
    masses = np.asarray(sim.masses, np.float64)
    volumes = np.asarray(sim.volumes, np.float64)
    if r_p == 1.0:
        ident_b = np.arange(scene.num_boundary, dtype=np.int64)
        return Downsampled(scene, np.arange(n, dtype=np.int64), ident_b)
    if clusters is not None:
        clusters = check_clusters(clusters, scene, r_p)
        labels = clusters.labels
    else:
        # a parameter set implies its material: clusters never mix sets
        groups = scene.material if scene.material_set is None else scene.material_set
        labels = cluster_particles(scene.positions, r_p, groups=groups, weights=masses, seed=seed)
    k = int(labels.max()) + 1
    m_l = cluster_sums(masses, labels, k)
    v_l = cluster_sums(volumes, labels, k)
    pos_l = cluster_centroids(scene.positions, labels, masses)
    vel_l = (cluster_sums(np.asarray(scene.velocities, np.float64) * masses[:, None], labels, k) / m_l[:, None]).astype(np.float32)
    mat_l = np.zeros(k, np.int32)
    mat_l[labels] = scene.material
    set_l = None
    if scene.material_set is not None:
        set_l = np.zeros(k, np.int32)
        set_l[labels] = scene.material_set
    j_l = None
    if scene.volume_ratio is not None:
        j_l = (cluster_sums(np.asarray(scene.volume_ratio, np.float64) * volumes, labels, k) / v_l).astype(np.float32)
    boundary_l, owner_l = scene.boundary_positions, scene.boundary_obstacle
    b_labels = np.zeros(0, np.int64)
    if scene.num_boundary:
        assert scene.boundary_positions is not None
        b_labels = clusters.boundary_labels if clusters is not None else cluster_particles(scene.boundary_positions, r_p, seed=seed)
        boundary_l = cluster_centroids(scene.boundary_positions, b_labels)
        if scene.boundary_obstacle is not None:  # each cluster's obstacle: its members' most common one
            owner = np.asarray(scene.boundary_obstacle, np.int64) + 1  # -1 (no obstacle) counts as 0
            counts = np.zeros((int(b_labels.max()) + 1, int(owner.max()) + 1), np.int64)
            np.add.at(counts, (b_labels, owner), 1)
            owner_l = (counts.argmax(axis=1) - 1).astype(np.int32)
    low = replace(
        scene,
        positions=pos_l,
        material=mat_l,
        material_set=set_l,
        velocities=vel_l,
        masses=m_l.astype(np.float32),
        volumes=v_l.astype(np.float32),
        volume_ratio=j_l,
        boundary_positions=boundary_l,
        boundary_obstacle=owner_l,
        info={**scene.info, "r_p": r_p, "n_h": n, "cluster_seed": int(seed)},
        clusters=Clusters(labels.astype(np.int32), b_labels.astype(np.int32)),
    )
    return Downsampled(low, labels, b_labels)


def at_resolution(scene: Scene, r_p: float, seed: int = 0, clusters: Clusters | None = None) -> Scene:
    """``scene`` at particle resolution ``r_p``: the scene itself for ``r_p = 1``
    or when it already is at ``r_p`` (a scene made by :func:`downsample_scene`
    records its ``r_p`` in ``info``), else :func:`downsample_scene` seeded by
    ``seed`` (or rebuilt from ``clusters``, without clustering). Raises
    :class:`InvalidInputError` for a bad ``r_p`` or ``clusters``."""
    r_p = check_r_p(r_p)
    if r_p == 1.0 or scene.info.get("r_p") == r_p:
        return scene
    return downsample_scene(scene, r_p, seed=seed, clusters=clusters).scene


def on_grid(scene: Scene, n_grid: int | None, particles_per_cell: int | None = None, *, keep_particles: bool = False, calibrated: bool = False) -> Scene:
    """``scene`` on another grid of the same domain.

    By default the particles are seeded anew from the scene's spec
    (:meth:`~hybridmpm.scenes.SceneSpec.on_grid`: the same blocks, obstacles
    and wall faces, ``particles_per_cell`` per axis, default the spec's);
    with ``keep_particles`` the scene's own particles (positions, velocities,
    materials, masses and rest volumes, J) move onto the new grid unchanged,
    so that a state moves between the two grids exactly. ``n_grid`` None (or
    the scene's own grid with nothing else asked) returns ``scene`` itself.
    The result records its ``info["base_n_grid"]``: the grid of its
    full-resolution reference (:func:`full_resolution`).

    With ``calibrated`` the result runs the calibrated coarse material of
    its scene and grid (:func:`calibrate`): the one place a simulator's
    ``calibrated`` switch takes effect.

    Raises :class:`InvalidInputError` naming the field (``n_grid``,
    ``particles_per_cell``, ``blocks[i]``, ``obstacles[i]...``; ``scene`` for
    a scene without a spec, or an ``r_p`` clustered one, asked to reseed;
    ``calibrated`` where no fit exists for the scene and grid).
    """
    new = _on_grid(scene, n_grid, particles_per_cell, keep_particles)
    return calibrate(new) if calibrated else new


def calibrate(scene: Scene) -> Scene:
    """``scene`` (a registered scene moved to a coarser grid by :func:`on_grid`)
    with its calibrated coarse material: the constitutive parameters fitted
    for its scene and grid (:func:`hybridmpm.models.calibrated.calibration`,
    set by :func:`hybridmpm.mpm.params.with_calibration`;
    docs/correction.md "Rung 1"). Its spec keeps the scene's own material, so
    its full-resolution reference (:func:`full_resolution`) is unchanged;
    ``info["calibrated"]`` names the fit. Raises :class:`InvalidInputError`
    (field ``calibrated``, naming ``--calibrated``) where no fit exists: the
    scene on its own grid, another grid or lattice, a clustered scene."""
    from hybridmpm.models.calibrated import calibration  # the package's data: loaded when asked for
    from hybridmpm.mpm.params import with_calibration

    n = scene.params.resolved_n_grid()
    if scene.info.get("r_p", 1.0) < 1.0:
        raise InvalidInputError("calibrated: --calibrated applies to plain MPM on a coarser grid at r_p = 1; drop --calibrated or --r-p", "calibrated")
    if scene.spec is None or scene.info.get("kept_particles"):
        raise InvalidInputError("calibrated: --calibrated applies to a registered scene reseeded on a coarser grid (not its kept particles)", "calibrated")
    ppc = scene.spec.particles_per_cell
    fit = calibration(scene.name, n, int(scene.info.get("base_n_grid", n)), ppc)
    return replace(scene, params=with_calibration(scene.params, fit["params"]), info={**scene.info, "calibrated": fit["name"]})


def _on_grid(scene: Scene, n_grid: int | None, particles_per_cell: int | None, keep_particles: bool) -> Scene:
    if n_grid is None and particles_per_cell is None:
        return scene
    n0 = scene.params.resolved_n_grid()
    n = n0 if n_grid is None else n_grid
    if scene.spec is None:
        raise InvalidInputError("scene: only a scene built from a spec (a registered scene or a scene file) moves to another grid", "scene")
    if keep_particles:
        if particles_per_cell is not None:
            raise InvalidInputError("particles_per_cell: the particles are kept; leave it unset", "particles_per_cell")
        spec = scene.spec.on_grid(n)  # validates the grid against the scene; its lattice is not used
        solver = scene.make_solver(num_threads=1)
        info = {**scene.info, "base_n_grid": int(scene.info.get("base_n_grid", n0)), "kept_particles": True}
        return replace(
            scene,
            # the scene's own parameters (a block's parameter set is the built scene's, not the spec's) on the new grid
            params=replace(scene.params, n_grid=spec.params.n_grid, walls=spec.params.walls, colliders=spec.params.colliders),
            masses=np.asarray(solver.masses, np.float32),
            volumes=np.asarray(solver.volumes, np.float32),
            info=info,
        )
    if scene.info.get("r_p", 1.0) < 1.0:
        raise InvalidInputError("scene: an r_p-clustered scene keeps its particles on another grid (keep_particles=True), or move the grid first", "scene")
    if n == n0 and (particles_per_cell is None or particles_per_cell == scene.spec.particles_per_cell):
        return scene
    new = scene.spec.on_grid(n, particles_per_cell).build()
    new.name = scene.name
    return new


def with_integrator(scene: Scene, integrator: str | None) -> Scene:
    """``scene`` stepped by ``integrator`` (one of
    :data:`hybridmpm.mpm.params.INTEGRATORS`; None: the scene's own). Its
    spec, the full-resolution reference (:func:`full_resolution`), keeps the
    scene's own. The projection steps water in the box walls and around
    free-slip obstacles, with rigid bodies: a scene with another material or an
    obstacle with friction is refused. Raises
    :class:`InvalidInputError` naming ``integrator`` (docs/large-step.md)."""
    if integrator is None or integrator == scene.params.integrator:
        return scene
    params = replace(scene.params, integrator=integrator)
    params.validate()  # the name, and no obstacles with friction for the projection
    if integrator != INTEGRATORS[0]:
        other = np.flatnonzero(np.asarray(scene.material) != MATERIAL_WATER)
        if other.size:
            name = {code: n for n, code in MATERIALS.items()}.get(int(scene.material[other[0]]), "another material")
            raise InvalidInputError(
                f"integrator: the {integrator} integrator steps water only, and {scene.name} holds {other.size} particles of {name}: use integrator 'explicit'",
                "integrator",
            )
    return replace(scene, params=params, info={**scene.info, "integrator": integrator})


def full_resolution(scene: Scene) -> Scene:
    """The full-resolution scene ``scene`` stands for: itself, unless it was
    clustered to ``r_p < 1`` or moved to another grid than the one it was
    made for (:func:`on_grid`); then the spec's scene on that grid (the
    reference of every error). Raises :class:`InvalidInputError` (field
    ``scene``) if such a scene has no spec to rebuild it from."""
    n = scene.params.resolved_n_grid()
    base = int(scene.info.get("base_n_grid", n))
    if scene.info.get("r_p", 1.0) >= 1.0 and base == n and not scene.info.get("kept_particles"):
        return scene
    if scene.spec is None:
        raise InvalidInputError("scene: the reference runs at full resolution; this scene has no spec to rebuild it from", "scene")
    spec = scene.spec
    if spec.params.resolved_n_grid() != base or spec.particles_per_cell != int(spec.info.get("base_particles_per_cell", spec.particles_per_cell)):
        spec = spec.on_grid(base, int(spec.info.get("base_particles_per_cell", 2)))
    full = spec.build()
    full.name = scene.name
    return full


def temporal_downsample(positions: np.ndarray, r_t: int) -> np.ndarray:
    """Keep every ``r_t``-th frame: [T, N, D] → [ceil(T / r_t), N, D] (frame 0 kept)."""
    return np.asarray(positions)[:: check_r_t(r_t)]


__all__ = [
    "KMEANS_SEEDS",
    "PAPER_R_P",
    "PAPER_R_T",
    "Downsampled",
    "at_resolution",
    "check_clusters",
    "check_r_p",
    "check_r_t",
    "cluster_centroids",
    "cluster_particles",
    "cluster_sums",
    "downsample_scene",
    "full_resolution",
    "kmeans_seed",
    "on_grid",
    "temporal_downsample",
    "with_integrator",
]
