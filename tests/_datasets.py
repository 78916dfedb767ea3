"""Small synthetic datasets in the training layout (``hybridmpm.data``: one ``.npz`` per split and
``metadata.json`` with the training split's statistics), for the training tests."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def write_dataset(directory: Path, splits: dict[str, dict[str, Any]], meta: dict[str, Any]) -> None:
    """Writes ``splits`` (split name -> {trajectory name: (positions [T, N, 2], types [N])}) and their
    metadata: ``meta`` with the training split's statistics."""
    from hybridmpm.data import compute_statistics, write_metadata, write_split

    for split, trajs in splits.items():
        write_split(directory / f"{split}.npz", trajs)
    write_metadata(directory / "metadata.json", {**meta, **compute_statistics(splits["train"])})


def split_names(n_traj: int) -> list[str]:
    """The split of each of ``n_traj`` trajectories: all but the last two train, then one validation, one test."""
    return ["train"] * (n_traj - 2) + ["valid", "test"]


def drag_dataset(directory: Path, n_traj: int = 6, frames: int = 40, n: int = 60, k: float = 0.2, seed: int = 0, scene: str | None = None) -> None:
    """Particles far apart, each moving under gravity and linear drag:
    a = g·dt² − k·v (per step); learnable from the velocity history."""
    rng = np.random.default_rng(seed)
    g = np.array([0.0, -2e-5])
    splits: dict[str, dict[str, Any]] = {"train": {}, "valid": {}, "test": {}}
    for i, split in enumerate(split_names(n_traj)):
        grid = np.stack(np.meshgrid(np.linspace(0.25, 0.75, 8), np.linspace(0.3, 0.8, 8)), -1).reshape(-1, 2)[:n]
        x = np.empty((frames + 1, n, 2))
        x[0] = grid
        v = rng.normal(0, 3e-3, (n, 2))
        for t in range(frames):
            v = v + g - k * v
            x[t + 1] = x[t] + v
        splits[split][f"simulation_trajectory_{i:05d}"] = (x.astype(np.float32), np.full(n, 5, np.int64))
    meta = {"bounds": [[0.02, 0.98]] * 2, "sequence_length": frames, "default_connectivity_radius": 0.02, "dim": 2, "dt": 2.5e-3, "r_t": 1, "n_grid": 128}
    write_dataset(directory, splits, {**meta, **({"scene": scene} if scene else {})})
