"""Pictures and exports of trajectories.

- :func:`render_gif` — an animated GIF (frames tinted by solver for a hybrid run);
- :func:`plot_timeline` — error and safeguard score over time, MPM shaded (paper Fig. 7);
- :func:`export_points` — a PLY / VTU point-cloud sequence for Blender or ParaView.
"""

from hybridmpm.render.gif import render_gif
from hybridmpm.render.pointcloud import FORMATS, export_points
from hybridmpm.render.timeline import mpm_spans, plot_timeline

__all__ = ["FORMATS", "export_points", "mpm_spans", "plot_timeline", "render_gif"]
