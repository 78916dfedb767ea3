"""Scenes: declarative specs, the paper's domains and their random initial conditions.

- :class:`Scene` — parameters + initial particles (+ static boundary particles).
- :class:`SceneSpec` — the declarative, TOML/JSON-serialisable description a
  scene is built from (:mod:`hybridmpm.scenes.spec`).
- :func:`collider_sdf` / :func:`boundary_particles` — an obstacle's signed
  distance and the network's static particles on it; reading and checking a
  scene file's obstacles (:mod:`hybridmpm.scenes.obstacles`; mesh obstacles
  in :mod:`hybridmpm.scenes.obstacle_mesh`).
- :class:`ParticleSet` — which particles are fluid, which boundary (one place
  pads and slices).
- :func:`downsample_scene` / :func:`at_resolution` — ``r_p`` clustering
  (paper Sec. 3.1.1, :mod:`hybridmpm.scenes.resolution`).
- :data:`DOMAINS` — seeded generators for ``water2d``, ``sand2d``,
  ``water_ramps2d``, ``sand_ramps2d``, ``water_sand2d``, ``water3d``,
  ``sand3d``, ``dam_break2d``, its 3D twin ``dam_break3d`` and
  ``paddle3d`` (``dam_break3d`` with a paddle downstream, the page's
  default 3D scene) (:mod:`hybridmpm.scenes.registry`).

>>> from hybridmpm.scenes import make_scene
>>> scene = make_scene("water_ramps2d", seed=3)
>>> sim = scene.make_solver()
"""

from hybridmpm.scenes.core import Clusters, Scene, hydrostatic_volume_ratio, lattice, wall_face
from hybridmpm.scenes.obstacles import boundary_particles, collider_sdf
from hybridmpm.scenes.particles import ParticleSet, pad_boundary
from hybridmpm.scenes.registry import (
    DOMAINS,
    PAPER_FRAMES,
    dam_break2d,
    dam_break2d_spec,
    dam_break3d_spec,
    make_scene,
    paddle3d_spec,
    registered_name,
    sand2d,
    sand3d,
    sand_ramps2d,
    scene_spec,
    water2d,
    water3d,
    water_ramps2d,
    water_sand2d,
)
from hybridmpm.scenes.resolution import PAPER_R_P, PAPER_R_T, at_resolution, downsample_scene
from hybridmpm.scenes.spec import MATERIALS, Block, SceneSpec

__all__ = [
    "DOMAINS",
    "MATERIALS",
    "PAPER_FRAMES",
    "PAPER_R_P",
    "PAPER_R_T",
    "Block",
    "Clusters",
    "ParticleSet",
    "Scene",
    "SceneSpec",
    "at_resolution",
    "boundary_particles",
    "collider_sdf",
    "dam_break2d",
    "dam_break2d_spec",
    "dam_break3d_spec",
    "downsample_scene",
    "hydrostatic_volume_ratio",
    "lattice",
    "make_scene",
    "pad_boundary",
    "paddle3d_spec",
    "registered_name",
    "sand2d",
    "sand3d",
    "sand_ramps2d",
    "scene_spec",
    "wall_face",
    "water2d",
    "water3d",
    "water_ramps2d",
    "water_sand2d",
]
