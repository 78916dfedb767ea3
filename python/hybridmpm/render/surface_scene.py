"""The surface settings of a scene and of a frame of its run: the keyword
arguments of :func:`~hybridmpm.render.surface.surface_mesh` /
:func:`~hybridmpm.render.surface.surface_contours` (the wall faces, the cell
size, the obstacles and bodies the surface ends on, each particle's volume)
from a scene's :class:`~hybridmpm.mpm.MpmParams` and a trajectory's poses.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hybridmpm.conventions import GNS_KINEMATIC, GNS_TYPE_OF_MATERIAL, MATERIALS
from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm.bodies import BodyTrack, as_body_track
from hybridmpm.render.surface_field import PosedBody
from hybridmpm.scenes import wall_face
from hybridmpm.scenes.obstacles import obstacles_at


def rest_densities(params: Any, particle_type: Any) -> np.ndarray:
    """The rest density [kg/m³] of each particle of GNS type ``particle_type``
    int [N] under a scene's :class:`~hybridmpm.mpm.MpmParams`: its material's
    parameter set where the scene holds exactly one further set of that
    material (a preset block: a jelly of ``jello``, ``mud``, ...), else the
    material's default set (with several further sets of one material, the
    default too: a trajectory does not carry each particle's set); 1 for
    kinematic particles."""
    pt = np.asarray(particle_type)
    rho = np.ones(len(pt), np.float64)
    for name, code in MATERIALS.items():
        group = params.table(name)  # the model's scene-level table (MpmParams.water, ..., or .tables)
        own = [g for g in params.sets if type(g) is type(group)]
        density = float((own[0] if len(own) == 1 else group).density)
        rho[pt == GNS_TYPE_OF_MATERIAL[code]] = density
    return rho


def surface_settings(params: Any, particle_type: Any = None, masses: Any = None) -> dict[str, Any]:
    """The keyword arguments of :func:`~hybridmpm.render.surface.surface_mesh` / :func:`~hybridmpm.render.surface.surface_contours`
    for a scene's :class:`~hybridmpm.mpm.MpmParams`: ``domain`` (the wall faces
    ``(cells − 1)·dx`` in from every side, :func:`~hybridmpm.scenes.wall_face`),
    ``dx`` = 1/n_grid, ``obstacles`` (the colliders where the scene puts
    them; a frame of a run whose obstacles move: :func:`posed_settings`) and, given
    ``particle_type`` int [N] and ``masses`` float [N] [kg], ``volumes`` =
    mass / rest density of the particle's material (:func:`rest_densities`;
    0 for kinematic particles)."""
    n = params.resolved_n_grid()
    face = wall_face(params)
    out: dict[str, Any] = {
        "domain": ([face] * params.dim, [1.0 - face] * params.dim),
        "dx": 1.0 / n,
        "obstacles": list(params.colliders),
    }
    if particle_type is not None and masses is not None:
        pt = np.asarray(particle_type)
        m = np.asarray(masses, np.float64)
        rho = rest_densities(params, pt)
        out["volumes"] = np.where(pt == GNS_KINEMATIC, 0.0, m / rho)
    return out


def pose_track(bodies: Any) -> BodyTrack | None:
    """The ``bodies`` argument of :func:`posed_settings` and
    :func:`~hybridmpm.render.surface.export_surfaces` as one checked
    :class:`~hybridmpm.mpm.bodies.BodyTrack`: a track as it is; ``(bodies as
    given, body_center [T, B, D] [m], body_rotation [T, B, D, D])`` made into
    one (:func:`~hybridmpm.mpm.bodies.as_body_track`); None (or no bodies, or
    no centres) None. A caller that goes over many frames calls it once and
    hands the track on. Raises :class:`InvalidInputError` naming ``bodies``
    (neither), ``body_center`` or ``body_rotation``."""
    if bodies is None or isinstance(bodies, BodyTrack):
        return bodies
    if not isinstance(bodies, (tuple, list)) or len(bodies) != 3:
        raise InvalidInputError(f"bodies: expected a BodyTrack or (bodies as given, body_center, body_rotation), got {type(bodies).__name__}", "bodies")
    return as_body_track(*bodies)


def posed_settings(settings: dict[str, Any], obstacle_centers: Any, t: int, bodies: Any = None) -> dict[str, Any]:
    """``settings`` (:func:`surface_settings`) for frame ``t`` of a run whose
    obstacles move: its ``obstacles`` translated to ``obstacle_centers[t]``
    (float [T, C, D] [m], a trajectory's
    :attr:`~hybridmpm.trajectory.Trajectory.obstacle_centers`;
    :func:`~hybridmpm.scenes.obstacles.obstacles_at`), so that the surface
    ends on each obstacle where it is in that frame; with ``bodies`` (a
    :class:`~hybridmpm.mpm.bodies.BodyTrack`, or ``(bodies as given,
    body_center [T, B, D], body_rotation [T, B, D, D])``: :func:`pose_track`)
    each body at frame ``t`` added as a
    :class:`~hybridmpm.render.surface_field.PosedBody`: the surface ends on it
    too. ``obstacle_centers`` and ``bodies`` None: ``settings`` as they are.
    Raises :class:`InvalidInputError` naming ``obstacle_centers`` (not
    [T, C, D] for the settings' C obstacles, not finite), ``bodies``,
    ``body_center`` (no row for frame ``t``) or ``body_rotation``
    (:func:`pose_track`)."""
    out = settings
    if obstacle_centers is not None:
        oc = np.asarray(obstacle_centers)
        if oc.ndim != 3 or not 0 <= t < oc.shape[0]:
            raise InvalidInputError(f"obstacle_centers: expected [T, C, D] with a row for frame {t}, got {list(oc.shape)}", "obstacle_centers")
        out = {**settings, "obstacles": obstacles_at(settings.get("obstacles", ()), oc[t])}
    track = pose_track(bodies)
    if track is not None:
        if not 0 <= t < track.num_frames:
            raise InvalidInputError(f"body_center: expected [T, B, D] with a row for frame {t}, got {list(track.center.shape)}", "body_center")
        posed = [PosedBody(b, track.center[t, i], track.rotation[t, i]) for i, b in enumerate(track.shapes)]
        out = {**out, "obstacles": [*out.get("obstacles", ()), *posed]}
    return out


__all__ = ["pose_track", "posed_settings", "rest_densities", "surface_settings"]
