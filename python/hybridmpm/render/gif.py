"""Render trajectories to an animated GIF (matplotlib frames, imageio writer)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.conventions import GNS_ELASTIC, GNS_GOOP, GNS_KINEMATIC, GNS_SAND, GNS_SNOW, GNS_WATER
from hybridmpm.mpm.bodies import BodyTrack, as_body_track
from hybridmpm.render.bodies import local_mesh, local_outline, place

#: colours by GNS particle type: water blue, sand ochre, jelly (elastic) a translucent red, snow white,
#: mud (viscoplastic) brown, obstacles grey
_COLOURS = {
    GNS_WATER: "#1f77b4",
    GNS_SAND: "#d2a25a",
    GNS_ELASTIC: "#e0457b",
    GNS_SNOW: "#fbfdff",
    GNS_GOOP: "#6b4226",
    GNS_KINEMATIC: "#444444",
}
#: opacity by GNS particle type (the rest opaque): jelly is translucent
_ALPHA = {GNS_ELASTIC: 0.55}
#: rigid bodies: a wood fill and a darker outline (docs/bodies.md "Pictures and exports")
BODY_FILL = "#b07a3c"
BODY_EDGE = "#5a3a17"
#: background of a scene with snow (white snow on the default white would vanish)
SNOW_BACKGROUND = "#c9d3df"


def particle_colours(particle_type: np.ndarray) -> np.ndarray:
    """RGBA in [0, 1], float64 [N, 4], of each particle by its GNS type
    (:data:`_COLOURS`, :data:`_ALPHA`; an unknown type grey)."""
    from matplotlib.colors import to_rgba

    table = {t: to_rgba(c, _ALPHA.get(t, 1.0)) for t, c in _COLOURS.items()}
    grey = to_rgba("#7f7f7f")
    return np.array([table.get(int(t), grey) for t in np.asarray(particle_type).ravel()], np.float64).reshape(-1, 4)


#: frame background / title colour by solver (hybrid renders)
_SOLVER_BG = {"mpm": "#fde9d4", "neural": "#e6f0fb"}
_SOLVER_FG = {"mpm": "#b35900", "neural": "#1f5fa8"}


def render_gif(
    positions: np.ndarray,
    particle_type: np.ndarray,
    path: str | Path,
    *,
    dt_frame: float,
    max_frames: int = 120,
    fps: int = 24,
    size_px: int = 360,
    title: str = "",
    frame_solver: np.ndarray | None = None,
    overlay: list[np.ndarray] | None = None,
    bodies: BodyTrack | Sequence[Any] | None = (),
    body_center: np.ndarray | None = None,
    body_rotation: np.ndarray | None = None,
) -> Path:
    """Write ``positions`` [T, N, D] as an animated GIF at ``path``.

    2D: particles coloured by material (water blue, sand ochre, jelly a
    translucent red, snow white on a grey-blue background, mud brown:
    :func:`particle_colours`); 3D: the x–y projection shaded by depth z
    (water alone in blues; with another material, each in its colour,
    darker with depth).
    At most ``max_frames`` evenly spaced frames are drawn. ``frame_solver``
    [T] of "mpm" / "neural" tints each frame by the solver that produced it
    (MPM: warm background, neural: cool) and names it in the title.
    ``overlay`` polylines [P, 2] (domain coordinates, e.g. a sketch) are drawn
    over every frame. ``bodies`` (a :class:`~hybridmpm.mpm.bodies.BodyTrack`
    of T frames, a rollout's :attr:`~hybridmpm.sim.Rollout.bodies`; or the
    scene's :class:`~hybridmpm.mpm.bodies.Body` list at ``body_center``
    float [T, B, D] [m] and ``body_rotation`` [T, B, D, D], a trajectory's
    arrays, made into a track once here: :func:`~hybridmpm.mpm.bodies.as_body_track`)
    are drawn over the particles in :data:`BODY_FILL`: in 2D their outline
    filled, in 3D their silhouette in the x–y projection; without the arrays
    (or with ``bodies`` None), none. Returns the path.

    Raises :class:`ValueError` for ``positions`` not [T, N, 2|3] and
    :class:`~hybridmpm.errors.InvalidInputError` naming ``body_center`` or
    ``body_rotation`` for poses that are not the bodies' over the T frames.
    """
    import imageio.v3 as iio
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    positions = np.asarray(positions)
    if positions.ndim != 3 or positions.shape[2] not in (2, 3):
        raise ValueError(f"positions: expected shape [T, N, 2|3], got {positions.shape}")
    t_count, _, dim = positions.shape
    idx = np.unique(np.linspace(0, t_count - 1, min(max_frames, t_count)).round().astype(int))
    types = np.asarray(particle_type).ravel()
    colours = particle_colours(types)
    materials = set(np.unique(types).tolist()) - {GNS_KINEMATIC}
    background = SNOW_BACKGROUND if GNS_SNOW in materials else "white"
    track = as_body_track(bodies, body_center, body_rotation, t_count=t_count)
    fig, ax = _figure(size_px)
    frames = []
    for i in idx:
        ax.clear()
        p = positions[i]
        tag = None if frame_solver is None else str(frame_solver[i])
        ax.set_facecolor(background if tag is None else _SOLVER_BG.get(tag, background))
        if dim == 2:
            ax.scatter(p[:, 0], p[:, 1], s=1.0, c=colours, linewidths=0)
        elif materials <= {GNS_WATER}:
            order = np.argsort(-p[:, 2])
            ax.scatter(p[order, 0], p[order, 1], s=1.0, c=p[order, 2], cmap="Blues_r", vmin=0, vmax=1, linewidths=0)
        else:
            order = np.argsort(-p[:, 2])
            shade = colours[order].copy()
            shade[:, :3] *= (1.0 - 0.45 * np.clip(p[order, 2], 0.0, 1.0))[:, None]
            ax.scatter(p[order, 0], p[order, 1], s=1.0, c=shade, linewidths=0)
        if track is not None:
            for k, body in enumerate(track.shapes):
                ax.fill(*_silhouette(body, track.center[i, k], track.rotation[i, k]).T, facecolor=BODY_FILL, edgecolor=BODY_EDGE, lw=0.8, zorder=3)
        for line in overlay or []:
            ax.plot(line[:, 0], line[:, 1], color="#d62728", lw=1.5, alpha=0.8)
        _frame_axes(ax)
        label = f"{title}  t = {i * dt_frame:.3f} s" + (f"  [{tag}]" if tag else "")
        ax.set_title(label, fontsize=8, color=_SOLVER_FG.get(tag or "", "black"))
        fig.canvas.draw()
        frames.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())  # type: ignore[attr-defined]
    plt.close(fig)
    path = Path(path)
    iio.imwrite(path, np.stack(frames), extension=".gif", duration=1000 / fps, loop=0)
    return path


def _figure(size_px: int) -> tuple[Any, Any]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dpi = 100
    return plt.subplots(figsize=(size_px / dpi, size_px / dpi), dpi=dpi)


def _frame_axes(ax: Any) -> None:
    """The unit domain, square, no ticks: every frame's axes."""
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def frame_pixel(xy: Sequence[float], size_px: int = 360) -> tuple[int, int]:
    """The (row, column) of domain point ``xy`` [m] (x, y) in a frame of :func:`render_gif` of ``size_px``."""
    import matplotlib.pyplot as plt

    fig, ax = _figure(size_px)
    _frame_axes(ax)
    ax.set_title("t", fontsize=8)
    fig.canvas.draw()
    col, row_up = ax.transData.transform((float(xy[0]), float(xy[1])))
    height = fig.canvas.get_width_height()[1]
    plt.close(fig)
    return int(round(height - row_up - 0.5)), int(round(col - 0.5))


def _silhouette(body: Any, center: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """A body's outline in the x–y plane at its pose [K, 2]: its own in 2D, the convex hull of its mesh's projection in 3D."""
    if len(center) == 2:
        return place(local_outline(body), center, rotation)
    from scipy.spatial import ConvexHull  # import time: scipy loads only when a 3D body is drawn

    xy = place(local_mesh(body)[0], center, rotation)[:, :2]
    return xy[ConvexHull(xy).vertices]
