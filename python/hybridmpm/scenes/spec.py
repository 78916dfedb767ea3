"""Declarative scene specs: domain, grid, materials, walls, particle blocks, obstacles.

A :class:`SceneSpec` is the whole description of an initial condition and its
solver settings, small enough to keep beside a dataset and to edit by hand.
It loads from and saves to TOML or JSON (chosen by the file suffix)::

    name = "two_blocks"
    dim = 2
    n_grid = 128
    dt_frame = 0.0025
    frames = 600

    [walls]
    cells = 3
    condition = "separate"
    friction = 0.0

    [walls.faces.y-]        # optional per-face overrides; y- is the floor
    friction = 0.5

    [[blocks]]
    material = "water"
    lo = [0.1, 0.05]
    hi = [0.3, 0.35]
    velocity = [0.5, 0.0]

    [[blocks]]              # a model or a preset, and its parameters
    material = "elastic"    # water, sand, elastic, snow, viscoplastic; jello, rubber, ...
    E = 2.0e5
    nu = 0.3
    lo = [0.5, 0.5]
    hi = [0.6, 0.6]

    [[obstacles]]
    shape = "box"
    center = [0.6, 0.3]
    half_extents = [0.15, 0.012]
    angle_deg = -20.0

    [[bodies]]              # a rigid body the fluid moves (docs/bodies.md)
    shape = "box"           # or "sphere" / "circle" (radius), "capsule" (radius, half_height), "mesh" (3D: path)
    center = [0.5, 0.5]
    half_extents = [0.06, 0.04]
    density = 500.0         # kg/m³ (or mass, kg per unit depth in 2D)

Obstacles (boxes, spheres, 3D triangle meshes, optionally on a keyframed
path) are read, checked, written back and sampled by
:mod:`hybridmpm.scenes.obstacles`, which this module imports (never the
reverse); docs/obstacles.md lists every key. A mesh's ``path`` is relative to
the scene file's folder (:meth:`SceneSpec.load`; ``confine=True`` keeps it
inside that folder). :func:`~hybridmpm.scenes.obstacles.collider_sdf` and
:func:`~hybridmpm.scenes.obstacles.boundary_particles` stay importable from
here.

:meth:`SceneSpec.build` turns it into a :class:`~hybridmpm.scenes.Scene`:
each block is filled with a cell-centred lattice at spacing
``dx / particles_per_cell``; a particle of a later block that falls inside an
earlier block is dropped (overlapping blocks form their union), and so is a
particle inside an obstacle (``sdf < 0``; or within ``obstacle_clearance_cells``
grid cells of its surface when that is set), so a block resting on or
touching an obstacle keeps all its particles. Dropped particles are counted
per block in ``scene.info["dropped_particles"]``; a block that loses all its
particles, or more than :data:`MAX_OBSTACLE_DROP_FRACTION` of them to
obstacles, is an error. Obstacles become MPM colliders and, for the network,
static boundary particles (GNS type 3) on a shell one spacing thick inside
their surface (GNS WaterRamps represents its ramps the same way).

A block's material is a model of the core (``water``, ``sand``, ``elastic``, ``snow``,
``viscoplastic``, ...: :data:`hybridmpm.materials.MODELS`) or a preset (``jello``, ``rubber``, ``snow``, ``mud``,
``plasticine``, ``honey``, ``soil``: :data:`hybridmpm.materials.PRESETS`),
with the model's parameters as keys of the block (``E``, ``nu``, ``density``,
``model``, ``theta_c``, ``theta_s``, ``hardening``, ``yield_stress``,
``viscosity``; each model's keys are its schema's, :mod:`hybridmpm.materials`). A block naming a model starts
from the scene's table of that model (``[water]``, ``[sand]``: the scene-level
parameters), a block naming a preset from the preset, and the block's own keys
override either. Blocks whose parameters differ from the scene's table become
parameter sets of the solver (:attr:`~hybridmpm.mpm.MpmParams.sets`), one per
distinct set.

Walls (``[walls]``) take one ``condition`` (``sticky``, ``slip``,
``separate``) and Coulomb ``friction`` for every face, and optional per-face
overrides in ``[walls.faces.<face>]`` with faces ``x-``, ``x+``, ``y-`` (the
floor; y is up), ``y+``, ``z-``, ``z+`` (3D only); TOML needs quotes around
names with ``+`` (``[walls.faces."x+"]``). See :class:`~hybridmpm.mpm.WallParams`.
"""

from __future__ import annotations

import itertools
import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.conventions import CONNECTIVITY_RADIUS as DEFAULT_CONNECTIVITY_RADIUS
from hybridmpm.conventions import MATERIALS
from hybridmpm.errors import InvalidInputError
from hybridmpm.files import check_nesting, loads_json, read_text_file
from hybridmpm.limits import check_allocation
from hybridmpm.materials import Material, block_keys, material_from_block, scene_bases
from hybridmpm.mpm import DT_FRAME, INTEGRATORS, MpmParams
from hybridmpm.mpm.bodies import check_bodies
from hybridmpm.scenes.body_mesh import check_overlaps, resolve_mesh_body
from hybridmpm.scenes.core import BYTES_PER_PARTICLE, Scene, hydrostatic_volume_ratio, lattice, wall_cells_for, wall_face
from hybridmpm.scenes.obstacles import (
    MAX_OBSTACLES,
    boundary_particles,
    check_vec,
    collider_sdf,
    guess_obstacle_field,
    is_number,
    mesh_paths_relative_to,
    obstacle_dict,
    obstacles_error,
    obstacles_on_grid,
    place_obstacles,
    read_obstacles,
    sample_boundary,
)

#: A block's keys besides its material's parameters.
_BLOCK_KEYS = frozenset({"material", "lo", "hi", "velocity", "hydrostatic"})

#: A block may lose at most this fraction of its lattice particles to
#: obstacles; more (or all of its particles, for any reason) is an error
#: naming the block, since such a block was almost certainly misplaced.
MAX_OBSTACLE_DROP_FRACTION = 0.5
#: Largest scene file read [bytes] (a scene is a few kB of TOML/JSON).
MAX_SCENE_FILE_BYTES = 16 * 2**20
#: Most particle blocks a scene may have (building is linear in the blocks and
#: the obstacles, of which it may have :data:`~hybridmpm.scenes.obstacles.MAX_OBSTACLES`:
#: overlaps are looked up in a spatial index of the earlier blocks).
MAX_BLOCKS = 4096
#: Fastest initial velocity of a block [m/s] per axis: faster than any frame's
#: substeps can follow (the CFL rule would need more than ``max_substeps``).
MAX_BLOCK_SPEED = 1000.0
#: Cells per axis of the index of earlier blocks that :meth:`SceneSpec.build` keeps.
_INDEX_CELLS = 16


@dataclass
class Block:
    """A box of particles of one material.

    ``material``: a model or a preset (:mod:`hybridmpm.materials`);
    ``lo``, ``hi``: opposite corners [m] (``lo < hi`` on every axis, inside the
    domain); ``velocity`` [m/s] (default 0); ``hydrostatic``: start water at
    hydrostatic rest below the block's top (only right for a block resting on
    the floor; see :func:`~hybridmpm.scenes.hydrostatic_volume_ratio`);
    ``params``: the block's own parameters (``{"E": 2e5}``), overriding its
    base: the scene's table of its model (a scene file's ``[water]`` or
    ``[sand]``; ``MpmParams.water``, ...) or its preset
    (:func:`~hybridmpm.materials.material_from_block`).
    """

    material: str
    lo: Sequence[float]
    hi: Sequence[float]
    velocity: Sequence[float] | None = None
    hydrostatic: bool = False
    params: dict[str, Any] = field(default_factory=dict)

    def resolved(self, where: str = "block", bases: dict[str, Material] | None = None) -> Any:
        """The block's :data:`~hybridmpm.materials.Material`: its base (the
        scene's table of its model, ``bases`` from
        :func:`~hybridmpm.materials.scene_bases`; the model's defaults without
        it; or its preset) with ``params`` applied. Raises
        :class:`InvalidInputError` naming the field."""
        return material_from_block(self.material, self.params, where, bases)

    def to_dict(self, bases: dict[str, Material] | None = None) -> dict[str, Any]:
        """The block as a scene file writes it: its keys that differ from its base (``bases`` as for :meth:`resolved`)."""
        d: dict[str, Any] = {"material": self.material, **block_keys(self.resolved(bases=bases), self.material, bases)}
        d["lo"], d["hi"] = [float(v) for v in self.lo], [float(v) for v in self.hi]
        if self.velocity is not None:
            d["velocity"] = [float(v) for v in self.velocity]
        if self.hydrostatic:
            d["hydrostatic"] = True
        return d


@dataclass
class SceneSpec:
    """Declarative scene: everything needed to rebuild an initial condition.

    ``params`` holds the solver settings (dim, grid, gravity, materials, walls)
    and the obstacles (``params.colliders``); ``blocks`` the particle blocks;
    ``dt_frame`` [s] and ``frames`` the rollout; ``particles_per_cell`` the
    lattice density per dimension (2: spacing dx/2); ``connectivity_radius``
    R [m] of the network's radius graph; ``info`` free-form facts (the
    generator's seed, ...), kept on save; ``obstacle_clearance_cells``: a
    particle closer than this many grid cells to an obstacle's surface is
    dropped too (default 0: only particles inside, ``sdf < 0``; the registered
    ramp domains keep their historical 0.5). ``registered`` is True only for a
    spec the registry made (:func:`~hybridmpm.scenes.registry.scene_spec`): it
    is never read from or written to a file or dict, and :meth:`on_grid` does
    not keep it, so a scene file is never a registered scene, whatever its
    ``name`` (:func:`~hybridmpm.scenes.registry.registered_name`).
    """

    name: str
    params: MpmParams
    blocks: list[Block]
    dt_frame: float = DT_FRAME
    frames: int = 300
    particles_per_cell: int = 2
    connectivity_radius: float = DEFAULT_CONNECTIVITY_RADIUS
    info: dict[str, Any] = field(default_factory=dict)
    obstacle_clearance_cells: float = 0.0
    registered: bool = field(default=False, compare=False, repr=False)

    @property
    def dim(self) -> int:
        return int(self.params.dim)

    @property
    def spacing(self) -> float:
        """Lattice spacing of the blocks [m]: ``dx / particles_per_cell``."""
        return 1.0 / (self.params.resolved_n_grid() * self.particles_per_cell)

    # ------------------------------------------------------------------ grids
    def on_grid(self, n_grid: int, particles_per_cell: int | None = None) -> SceneSpec:
        """The same scene on another grid of the same domain: a copy with
        ``n_grid`` cells per side, the same blocks and obstacles (in metres),
        the walls' faces where they were (:func:`~hybridmpm.scenes.core.wall_cells_for`:
        exact when ``face·n_grid`` is an integer, e.g. 128² → 64² or 64³ → 32³,
        else the nearest node inside), the obstacle clearance kept in metres
        and ``particles_per_cell`` per axis (default: the spec's own), so the
        lattice spacing becomes ``1 / (n_grid · particles_per_cell)``.

        ``info["base_n_grid"]`` and ``info["base_particles_per_cell"]`` record
        the grid and lattice the scene was made for (those of its reference,
        full-resolution MPM) and a dam break's
        ``info["spacing"]`` follows the new lattice.

        Raises :class:`InvalidInputError` naming the field when the grid is too
        coarse for the scene: ``n_grid`` (not an integer in [16, 4096], or too
        few cells for the walls), ``particles_per_cell`` (not in [1, 4]),
        ``blocks[i]`` (a side thinner than one cell), ``obstacles[i].half_extents``
        / ``obstacles[i].radius`` / ``obstacles[i].path`` (thinner than the
        solver holds: 2 cells for a box, a radius of 1.5 cells for a sphere, a
        node 1 cell inside for a mesh, whose signed distance is sampled again
        on the new grid).
        """
        if isinstance(n_grid, bool) or not isinstance(n_grid, (int, np.integer)) or not 16 <= int(n_grid) <= 4096:
            raise InvalidInputError(f"n_grid: must be an integer in [16, 4096], got {n_grid!r}", "n_grid")
        n = int(n_grid)
        ppc = self.particles_per_cell if particles_per_cell is None else particles_per_cell
        if isinstance(ppc, bool) or not isinstance(ppc, (int, np.integer)) or not 1 <= int(ppc) <= 4:
            raise InvalidInputError(f"particles_per_cell: must be an integer in [1, 4], got {ppc!r}", "particles_per_cell")
        n0 = self.params.resolved_n_grid()
        face = wall_face(self.params)
        cells = wall_cells_for(face, n)
        if 4 * cells >= n:
            raise InvalidInputError(
                f"n_grid: {n} cells per side are too few for this scene's walls (a band of {cells} cells keeps their faces at {face:.4g} m; "
                f"the band must stay under a quarter of the grid: n_grid > {4 * cells})",
                "n_grid",
            )
        dx = 1.0 / n
        for i, b in enumerate(self.blocks):
            side = float(np.min(np.asarray(b.hi, np.float64) - np.asarray(b.lo, np.float64)))
            if side < dx * (1.0 - 1e-6):
                raise InvalidInputError(
                    f"blocks[{i}]: {side:.4g} m thin, less than one cell of a {n} grid (dx = {dx:.4g} m); use n_grid >= {math.ceil(1.0 / side - 1e-6)}",
                    f"blocks[{i}]",
                )
            if min(b.lo) < dx or max(b.hi) > 1.0 - dx:
                raise InvalidInputError(f"blocks[{i}]: must lie inside [dx, 1 - dx] = [{dx:.4g}, {1 - dx:.4g}] on a {n} grid", f"blocks[{i}]")
        d = self.params.to_dict()
        d["n_grid"] = n
        d["walls"] = {**d["walls"], "cells": cells}
        params = MpmParams.from_dict(d)
        obstacles_on_grid(self.params.colliders, params, n)
        info = {
            **self.info,
            "base_n_grid": int(self.info.get("base_n_grid", n0)),
            "base_particles_per_cell": int(self.info.get("base_particles_per_cell", self.particles_per_cell)),
        }
        if "spacing" in info:
            info["spacing"] = dx / int(ppc)
        return SceneSpec(
            self.name,
            params,
            [Block(b.material, list(b.lo), list(b.hi), None if b.velocity is None else list(b.velocity), b.hydrostatic, dict(b.params)) for b in self.blocks],
            dt_frame=self.dt_frame,
            frames=self.frames,
            particles_per_cell=int(ppc),
            connectivity_radius=self.connectivity_radius,
            info=info,
            obstacle_clearance_cells=self.obstacle_clearance_cells * n / n0,
        )

    # ------------------------------------------------------------------ dict / files
    def to_dict(self) -> dict[str, Any]:
        """Plain, JSON/TOML-serialisable dict (no ``None`` values)."""
        p = self.params.to_dict()
        bases = scene_bases(self.params)
        d: dict[str, Any] = {
            "name": self.name,
            "dim": p["dim"],
            "n_grid": p["n_grid"],
            "dt_frame": float(self.dt_frame),
            "frames": int(self.frames),
            "particles_per_cell": int(self.particles_per_cell),
            "connectivity_radius": float(self.connectivity_radius),
            "gravity": p["gravity"],
            "cfl": p["cfl"],
            "max_substeps": p["max_substeps"],
            **({"integrator": p["integrator"]} if "integrator" in p else {}),
            "water": p["water"],
            "sand": p["sand"],
            "walls": p["walls"],
            "blocks": [b.to_dict(bases) for b in self.blocks],
            "obstacles": [obstacle_dict(c, raw) for c, raw in zip(self.params.colliders, p["colliders"])],
        }
        if p["substeps"] is not None:
            d["substeps"] = p["substeps"]
        if "bodies" in p:
            d["bodies"] = p["bodies"]
        if self.obstacle_clearance_cells:
            d["obstacle_clearance_cells"] = float(self.obstacle_clearance_cells)
        if self.info:
            d["info"] = _plain(self.info)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any], *, base_dir: str | os.PathLike[str] | None = None, confine: bool = False) -> SceneSpec:
        """Inverse of :meth:`to_dict`; validates every field (errors name it,
        e.g. ``blocks[1].hi``). Raises :class:`InvalidInputError`.

        A mesh obstacle's ``path`` is relative to ``base_dir`` (the working
        directory when ``None``); ``confine=True`` refuses a path that leaves
        ``base_dir`` (absolute, ``..``, or a link out), naming
        ``obstacles[i].path`` (:func:`~hybridmpm.scenes.obstacle_mesh.resolve_mesh_path`).

        A mesh body whose convex hull has more than
        :data:`~hybridmpm.scenes.body_mesh.MAX_HULL_FACES` triangles keeps a
        simplified hull (:func:`~hybridmpm.scenes.body_mesh.simplify_hull`,
        from a quarter of this scene's cell), each one reported in
        ``info["simplified_body_hulls"]`` (its ``field``, ``faces_given``,
        ``faces``, ``tolerance_m``: how far its surface moved inward at most
        [m], and ``n_grid``)."""
        if not isinstance(d, dict):
            raise InvalidInputError("scene: expected a table/object at the top level", "scene")
        allowed = {
            "name", "dim", "n_grid", "dt_frame", "frames", "particles_per_cell", "connectivity_radius", "gravity",
            "cfl", "max_substeps", "substeps", "water", "sand", "walls", "blocks", "obstacles", "info",
            "obstacle_clearance_cells", "bodies", "integrator",
        }  # fmt: skip
        unknown = sorted(set(d) - allowed)
        if unknown:
            raise InvalidInputError(f"{unknown[0]}: unknown scene field (allowed: {', '.join(sorted(allowed))})", unknown[0])
        dim = d.get("dim", 2)
        if dim not in (2, 3):
            raise InvalidInputError(f"dim: must be 2 or 3, got {dim!r}", "dim")
        pd: dict[str, Any] = {"dim": dim}
        for k in ("n_grid", "gravity", "cfl", "max_substeps", "substeps", "water", "sand", "walls", "integrator"):
            if k in d:
                pd[k] = d[k]
        # a mesh obstacle is checked here and sampled once the grid is known; a path is set aside until then
        pd["colliders"], pending = read_obstacles(d.get("obstacles", []), dim, base_dir, confine)
        raw_bodies = d.get("bodies", [])
        simplified: list[dict[str, Any]] = []  # mesh bodies whose hulls were cut to MAX_HULL_FACES (info["simplified_body_hulls"])
        if isinstance(raw_bodies, list):  # a mesh body's file is read against the scene's folder (MpmParams.from_dict names a non-list)
            g = d.get("n_grid", MpmParams(dim=dim).resolved_n_grid())  # the grid a hull is simplified against (a bad one is named below)
            g = g if isinstance(g, int) and not isinstance(g, bool) and 16 <= g <= 4096 else None
            raw_bodies = [
                resolve_mesh_body(b, f"bodies[{i}]", dim, base_dir, confine, n_grid=g, simplified=simplified) if isinstance(b, dict) else b
                for i, b in enumerate(raw_bodies)
            ]
        pd["bodies"] = raw_bodies
        if isinstance(d.get("blocks"), list) and len(d["blocks"]) > MAX_BLOCKS:
            raise InvalidInputError(f"blocks: {len(d['blocks'])} blocks, more than the {MAX_BLOCKS} a scene may have", "blocks")
        try:
            params = MpmParams.from_dict(pd)
            params.to_dict()
        except InvalidInputError as e:  # the solver calls obstacles "colliders"
            raise obstacles_error(e) from e
        except (TypeError, ValueError, AttributeError) as e:  # an unknown keyword or a value of the wrong type in a sub-table
            raise InvalidInputError(f"scene parameters: {e} (in {_guess_field(pd)})", _guess_field(pd)) from e
        n_grid = params.resolved_n_grid()
        if not isinstance(n_grid, int) or n_grid < 8:
            raise InvalidInputError(f"n_grid: must be an integer >= 8, got {n_grid!r}", "n_grid")
        place_obstacles(params, pending, n_grid, dim)
        check_bodies(params.bodies, dim, n_grid, params.walls.cells)
        check_overlaps(params.bodies, params.colliders, dim, n_grid)
        blocks_raw = d.get("blocks")
        if not isinstance(blocks_raw, list) or not blocks_raw:
            raise InvalidInputError("blocks: a scene needs at least one particle block", "blocks")
        blocks = []
        bases = scene_bases(params)  # a block naming a model starts from the scene's table of it
        for i, b in enumerate(blocks_raw):
            f = f"blocks[{i}]"
            if not isinstance(b, dict):
                raise InvalidInputError(f"{f}: expected a table/object", f)
            mat = b.get("material")
            keys = {k: v for k, v in b.items() if k not in _BLOCK_KEYS}
            resolved = material_from_block(mat, keys, f, bases)  # the model or preset and its keys, each checked
            if params.integrator != INTEGRATORS[0] and resolved.name != "water":
                raise InvalidInputError(
                    f"integrator: the {params.integrator} integrator steps water only, and {f} is {resolved.name} ({mat}): use integrator 'explicit'",
                    "integrator",
                )
            lo = check_vec(f"{f}.lo", b.get("lo"), dim)
            hi = check_vec(f"{f}.hi", b.get("hi"), dim)
            if np.any(hi <= lo):
                raise InvalidInputError(f"{f}.hi: must exceed lo on every axis", f"{f}.hi")
            dx = 1.0 / n_grid
            if lo.min() < dx or hi.max() > 1.0 - dx:
                raise InvalidInputError(f"{f}: must lie inside [dx, 1 - dx] = [{dx:.4g}, {1 - dx:.4g}]", f)
            vel = b.get("velocity")
            if vel is not None:
                v = check_vec(f"{f}.velocity", vel, dim)
                if np.any(np.abs(v) > MAX_BLOCK_SPEED):
                    raise InvalidInputError(f"{f}.velocity: at most {MAX_BLOCK_SPEED:g} m/s per axis, got {vel!r}", f"{f}.velocity")
            blocks.append(Block(str(mat), list(lo), list(hi), None if vel is None else [float(v) for v in vel], bool(b.get("hydrostatic", False)), keys))
        dt_frame = d.get("dt_frame", DT_FRAME)
        if not (isinstance(dt_frame, (int, float)) and math.isfinite(dt_frame) and dt_frame > 0):
            raise InvalidInputError(f"dt_frame: must be a finite number > 0, got {dt_frame!r}", "dt_frame")
        frames = d.get("frames", 300)
        if not (isinstance(frames, int) and frames >= 1):
            raise InvalidInputError(f"frames: must be an integer >= 1, got {frames!r}", "frames")
        ppc = d.get("particles_per_cell", 2)
        if not (isinstance(ppc, int) and 1 <= ppc <= 4):
            raise InvalidInputError(f"particles_per_cell: must be an integer in [1, 4], got {ppc!r}", "particles_per_cell")
        radius = d.get("connectivity_radius", DEFAULT_CONNECTIVITY_RADIUS)
        if not (isinstance(radius, (int, float)) and math.isfinite(radius) and 0 < radius < 0.5):
            raise InvalidInputError(f"connectivity_radius: must be in (0, 0.5) m, got {radius!r}", "connectivity_radius")
        info = d.get("info", {})
        if not isinstance(info, dict):
            raise InvalidInputError("info: expected a table/object", "info")
        clearance = d.get("obstacle_clearance_cells", 0.0)
        if isinstance(clearance, bool) or not (isinstance(clearance, (int, float)) and math.isfinite(clearance) and 0 <= clearance <= 4):
            raise InvalidInputError(f"obstacle_clearance_cells: must be a number in [0, 4] grid cells, got {clearance!r}", "obstacle_clearance_cells")
        return cls(
            str(d.get("name", "scene")),
            params,
            blocks,
            dt_frame=float(dt_frame),
            frames=frames,
            particles_per_cell=ppc,
            connectivity_radius=float(radius),
            info={**info, "simplified_body_hulls": simplified} if simplified else dict(info),
            obstacle_clearance_cells=float(clearance),
        )

    def save(self, path: str | Path) -> Path:
        """Write as TOML (``.toml``) or JSON (any other suffix); returns the path."""
        path = Path(path)
        d = self.to_dict()
        mesh_paths_relative_to(d["obstacles"], path.parent)  # when the mesh lies under the saved file's folder
        if path.suffix == ".toml":
            import tomli_w

            text = tomli_w.dumps(d)
        else:
            text = json.dumps(d, indent=2)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(text)
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path: str | Path, *, confine: bool = False) -> SceneSpec:
        """Read a TOML (``.toml``) or JSON file. Raises :class:`InvalidInputError`
        for a missing, unparsable or invalid file (the message names the field).

        Mesh obstacles' paths are relative to the file's folder. ``confine=True``
        is for scene files from an untrusted source (a served request): a
        mesh ``path`` that is absolute, contains ``..`` or resolves through a
        link outside the scene file's folder is refused, naming
        ``obstacles[i].path``."""
        path = Path(path)
        text = read_text_file(path, MAX_SCENE_FILE_BYTES, "scene", "scene file")
        toml = path.suffix == ".toml"
        if toml:
            check_nesting(text, "scene", toml=True)
            try:
                import tomllib
            except ModuleNotFoundError:  # Python 3.10
                import tomli as tomllib  # type: ignore[no-redef]
            try:
                d = tomllib.loads(text)
            except ValueError as e:  # tomllib.TOMLDecodeError is a ValueError
                raise InvalidInputError(f"scene file {path}: not valid TOML: {e}", "scene") from e
        else:
            d = loads_json(text, "scene")  # nesting checked before parsing
        return cls.from_dict(d, base_dir=path.parent, confine=confine)

    # ------------------------------------------------------------------ building
    def build(self) -> Scene:
        """Seed the particles and sample the boundary particles: a :class:`Scene`.

        A lattice particle is dropped if it lies inside an earlier block or
        inside an obstacle (``sdf < obstacle_clearance_cells·dx``; ``sdf < 0``
        by default). ``scene.info["dropped_particles"]`` then lists, per
        affected block, ``{"block": i, "lattice": n, "earlier_blocks": k,
        "obstacles": m}`` (absent when nothing was dropped).

        Raises :class:`InvalidInputError` naming the block (``blocks[i]``) if
        a block loses all its particles, or more than
        :data:`MAX_OBSTACLE_DROP_FRACTION` of them to obstacles.
        """
        dim = self.dim
        s = self.spacing
        dx = 1.0 / self.params.resolved_n_grid()
        clearance = self.obstacle_clearance_cells * dx
        pos_l, mat_l, vel_l, j_l, set_l = [], [], [], [], []
        # each block's parameter set: its model's default (at the model's code) or one of `sets` (5, 6, ...)
        bases = scene_bases(self.params)
        sets: list[Any] = list(self.params.sets)
        dropped: list[dict[str, int]] = []
        placed: list[tuple[np.ndarray, np.ndarray]] = []
        index: dict[tuple[int, ...], list[int]] = {}  # cell of a coarse index grid -> earlier blocks overlapping it
        counts = [int(np.prod(np.maximum(np.round((np.asarray(b.hi, np.float64) - np.asarray(b.lo, np.float64)) / s), 1))) for b in self.blocks]
        for i, n in enumerate(counts):
            check_allocation(f"blocks[{i}]", n * BYTES_PER_PARTICLE, f"{n} particles (lattice spacing {s:.3g} m = dx/{self.particles_per_cell})")
        check_allocation("blocks", sum(counts) * BYTES_PER_PARTICLE, f"{sum(counts)} particles in all")
        vol_l: list[np.ndarray] = []
        for i, b in enumerate(self.blocks):
            lo, hi = np.asarray(b.lo, np.float64), np.asarray(b.hi, np.float64)
            # a block whose sides are not whole lattice spacings (a scene moved to a grid such as 96² from 128²) is
            # filled exactly by a lattice stretched to its sides, each particle carrying its share of the block's volume
            per_axis = np.maximum(np.round((hi - lo) / s), 1)
            step = np.where(np.abs(per_axis * s - (hi - lo)) <= 1e-9, s, (hi - lo) / per_axis)
            p = lattice(lo, hi, s if np.all(step == s) else step)
            vol_l.append(np.full(len(p), float(np.prod(step)), np.float64))
            keep = np.ones(len(p), bool)
            cells = _index_cells(lo, hi)
            for j in sorted({j for cell in cells for j in index.get(cell, ())}):
                plo, phi = placed[j]
                keep &= ~np.all((p >= plo) & (p < phi), axis=1)
            for cell in cells:
                index.setdefault(cell, []).append(i)
            n_overlap = int(len(p) - keep.sum())
            for c in self.params.colliders:
                keep &= collider_sdf(c, p) >= clearance
            for body in self.params.bodies:  # counted as obstacles
                keep &= body.sdf(p) >= clearance
            n_obstacle = int(len(p) - keep.sum()) - n_overlap
            if n_overlap or n_obstacle:
                dropped.append({"block": i, "lattice": len(p), "earlier_blocks": n_overlap, "obstacles": n_obstacle})
            if n_obstacle > MAX_OBSTACLE_DROP_FRACTION * len(p) or not keep.any():
                where = f"blocks[{i}]"
                raise InvalidInputError(
                    f"{where}: {len(p) - int(keep.sum())} of its {len(p)} lattice particles would be dropped "
                    f"({n_obstacle} inside obstacles, {n_overlap} inside earlier blocks); a block may lose at most "
                    f"{MAX_OBSTACLE_DROP_FRACTION:.0%} to obstacles and must keep at least one particle: move or shrink it",
                    where,
                )
            p = p[keep]
            vol_l[-1] = vol_l[-1][keep]
            placed.append((lo, hi))
            pos_l.append(p)
            m = b.resolved(f"blocks[{i}]", bases)
            mat_l.append(np.full(len(p), m.code, np.int32))
            ps = m.to_params()
            if (k := self.params.set_index(ps, sets)) is None:
                sets.append(ps)
                k = self.params.set_index(ps, sets)
            set_l.append(np.full(len(p), k, np.int32))
            v = np.zeros(dim) if b.velocity is None else np.asarray(b.velocity, np.float64)
            vel_l.append(np.tile(v.astype(np.float32), (len(p), 1)))
            if b.hydrostatic and m.name == "water":
                j_l.append(hydrostatic_volume_ratio(p, float(hi[1]), self.params))
            else:
                j_l.append(np.ones(len(p), np.float32))
        positions = np.concatenate(pos_l).astype(np.float32)
        if len(positions) == 0:
            raise InvalidInputError("blocks: no particle left after removing overlaps with obstacles and earlier blocks", "blocks")
        volume_ratio = np.concatenate(j_l)
        boundary, owner = sample_boundary(self.params.colliders, dim, s, dx)
        # the solver's default volume is (dx/2)^D (2 particles per cell per axis); other lattices carry their own
        vol = np.concatenate(vol_l)
        volumes = None if self.particles_per_cell == 2 and np.all(vol == s**dim) else vol.astype(np.float32)
        material_set = np.concatenate(set_l)
        material = np.concatenate(mat_l)
        return Scene(
            name=self.name,
            params=self.params if len(sets) == len(self.params.sets) else replace(self.params, sets=sets),
            material_set=None if np.array_equal(material_set, material) else material_set,
            positions=positions,
            material=material,
            velocities=np.concatenate(vel_l).reshape(-1, dim).astype(np.float32),
            dt_frame=self.dt_frame,
            frames=self.frames,
            info={**self.info, "dropped_particles": dropped} if dropped else dict(self.info),
            volume_ratio=None if np.all(volume_ratio == 1.0) else volume_ratio,
            boundary_positions=boundary if len(boundary) else None,
            boundary_obstacle=owner if len(boundary) else None,
            connectivity_radius=self.connectivity_radius,
            spec=self,
            volumes=volumes,
        )


def _index_cells(lo: np.ndarray, hi: np.ndarray) -> list[tuple[int, ...]]:
    """The cells of an :data:`_INDEX_CELLS`-per-axis grid of the unit domain that the box ``[lo, hi]`` overlaps."""
    a = np.clip(np.floor(lo * _INDEX_CELLS).astype(int), 0, _INDEX_CELLS - 1)
    b = np.clip(np.floor(hi * _INDEX_CELLS).astype(int), 0, _INDEX_CELLS - 1)
    return list(itertools.product(*(range(x, y + 1) for x, y in zip(a, b))))


def _guess_field(pd: dict[str, Any]) -> str:
    """The first solver-parameter entry of a scene that is not a plain value of
    its expected kind (for an error that a bare ``float()`` raised)."""
    for k, v in pd.items():
        if k in ("water", "sand", "walls") and not isinstance(v, dict):
            return k
        if k == "colliders" and (f := guess_obstacle_field(v)) is not None:
            return f
        if k == "gravity" and not (isinstance(v, list) and all(is_number(x) for x in v)):
            return k
        if k in ("cfl", "n_grid", "max_substeps", "substeps") and v is not None and not is_number(v):
            return k
        if k == "integrator" and not isinstance(v, str):
            return k
        if isinstance(v, dict):
            for key, val in v.items():
                if key != "condition" and key != "faces" and not is_number(val):
                    return f"{k}.{key}"
    return "params"


def _plain(x: Any) -> Any:
    """Make numpy scalars/arrays in ``info`` serialisable."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


__all__ = [
    "BYTES_PER_PARTICLE",
    "MATERIALS",
    "MAX_OBSTACLES",
    "MAX_OBSTACLE_DROP_FRACTION",
    "Block",
    "SceneSpec",
    "boundary_particles",
    "collider_sdf",
]
