"""Pictures and exports of trajectories.

- :func:`render_gif` — an animated GIF (frames tinted by solver for a hybrid run);
- :func:`plot_timeline` — error and safeguard score over time, MPM shaded (paper Fig. 7);
- :func:`export_points` — a PLY / VTU point-cloud sequence for Blender or ParaView;
- :func:`surface_mesh` / :func:`surface_contours` — closed fluid surfaces per
  material (docs/mesh.md), :func:`export_surfaces` their file sequences;
- :func:`write_usd` — one USD file per run (docs/usd.md; the ``usd`` extra).
"""

from hybridmpm.render.gif import render_gif
from hybridmpm.render.pointcloud import FORMATS, export_points
from hybridmpm.render.surface import (
    MESH_FORMATS,
    SurfaceContours,
    SurfaceMesh,
    export_surfaces,
    surface_contours,
    surface_mesh,
    write_surface,
)
from hybridmpm.render.surface_scene import surface_settings
from hybridmpm.render.timeline import mpm_spans, plot_timeline
from hybridmpm.render.usd import write_usd

__all__ = [
    "FORMATS",
    "MESH_FORMATS",
    "SurfaceContours",
    "SurfaceMesh",
    "export_points",
    "export_surfaces",
    "mpm_spans",
    "plot_timeline",
    "render_gif",
    "surface_contours",
    "surface_mesh",
    "surface_settings",
    "write_surface",
    "write_usd",
]
