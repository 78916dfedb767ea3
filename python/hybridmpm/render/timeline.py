"""Timeline of a hybrid rollout (paper Fig. 7): grid-mass error and the
safeguard score over time, with the frames MPM produced shaded."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def mpm_spans(tags: np.ndarray) -> list[tuple[int, int]]:
    """Runs of consecutive ``"mpm"`` entries of ``tags`` as half-open index ranges ``(start, stop)``."""
    spans, start = [], None
    for i, t in enumerate(list(tags) + ["end"]):
        if t == "mpm" and start is None:
            start = i
        elif t != "mpm" and start is not None:
            spans.append((start, i))
            start = None
    return spans


def plot_timeline(
    path: str | Path,
    dt_step: float,
    tags: np.ndarray,
    score: np.ndarray,
    r_c: float,
    error: np.ndarray | None = None,
    title: str = "",
) -> Path:
    """Write a PNG: ``error`` [K] (grid-mass error per stored step, optional)
    and ``score`` s(t) [K] against time ``k·dt_step`` [s], MPM steps (``tags``
    [K] == "mpm") shaded, the threshold ``r_c`` dashed. Returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.arange(len(tags)) * dt_step
    rows = 2 if error is not None else 1
    fig, axes = plt.subplots(rows, 1, figsize=(7, 2.3 * rows + 0.4), sharex=True, squeeze=False)
    axs = axes[:, 0]
    for ax in axs:
        for a, b in mpm_spans(np.asarray(tags)):
            ax.axvspan(t[a] - 0.5 * dt_step, t[min(b, len(t) - 1)] - 0.5 * dt_step if b < len(t) else t[-1], color="#f4a259", alpha=0.25, lw=0)
    if error is not None:
        axs[0].plot(t, error, color="#1f5fa8", lw=1.2, label="hybrid")
        axs[0].set_ylabel("grid-mass error")
        axs[0].legend(loc="upper left", fontsize=8, title="shaded: MPM", title_fontsize=8)
    ax = axs[-1]
    ax.plot(t, score, color="#333333", lw=1.0)
    ax.axhline(r_c, color="#b35900", ls="--", lw=1.0, label=f"r_c = {r_c:g}")
    ax.set_ylim(-1.05, 1.05)
    ax.set_ylabel("s(t)")
    ax.set_xlabel("time [s]")
    ax.legend(loc="lower left", fontsize=8)
    if title:
        axs[0].set_title(title, fontsize=9)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


__all__ = ["mpm_spans", "plot_timeline"]
