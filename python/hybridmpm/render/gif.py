"""Render trajectories to an animated GIF (matplotlib frames, imageio writer)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hybridmpm.conventions import GNS_KINEMATIC, GNS_SAND, GNS_WATER

#: colours by GNS particle type
_COLOURS = {GNS_WATER: "#1f77b4", GNS_SAND: "#d2a25a", GNS_KINEMATIC: "#444444"}
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
) -> Path:
    """Write ``positions`` [T, N, D] as an animated GIF at ``path``.

    2D: particles coloured by type; 3D: the x–y projection, shaded by depth z.
    At most ``max_frames`` evenly spaced frames are drawn. ``frame_solver``
    [T] of "mpm" / "neural" tints each frame by the solver that produced it
    (MPM: warm background, neural: cool) and names it in the title.
    ``overlay`` polylines [P, 2] (domain coordinates, e.g. a sketch) are drawn
    over every frame. Returns the path.
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
    colours = np.array([_COLOURS.get(int(t), "#7f7f7f") for t in particle_type])
    dpi = 100
    fig, ax = plt.subplots(figsize=(size_px / dpi, size_px / dpi), dpi=dpi)
    frames = []
    for i in idx:
        ax.clear()
        p = positions[i]
        tag = None if frame_solver is None else str(frame_solver[i])
        if tag is not None:
            ax.set_facecolor(_SOLVER_BG.get(tag, "white"))
        if dim == 2:
            ax.scatter(p[:, 0], p[:, 1], s=1.0, c=colours, linewidths=0)
        else:
            order = np.argsort(-p[:, 2])
            ax.scatter(p[order, 0], p[order, 1], s=1.0, c=p[order, 2], cmap="Blues_r", vmin=0, vmax=1, linewidths=0)
        for line in overlay or []:
            ax.plot(line[:, 0], line[:, 1], color="#d62728", lw=1.5, alpha=0.8)
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        label = f"{title}  t = {i * dt_frame:.3f} s" + (f"  [{tag}]" if tag else "")
        ax.set_title(label, fontsize=8, color=_SOLVER_FG.get(tag or "", "black"))
        fig.canvas.draw()
        frames.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())  # type: ignore[attr-defined]
    plt.close(fig)
    path = Path(path)
    iio.imwrite(path, np.stack(frames), extension=".gif", duration=1000 / fps, loop=0)
    return path
