"""Small synthetic training inputs that the training tests share (tests/test_ddp.py,
tests/test_train_scaffold.py): a GNS dataset of particles under gravity and drag, water2d control
cases, and a tiny GNS training configuration. Cheap to make; enough to train a few steps on."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from hybridmpm.conventions import GNS_KINEMATIC, GNS_WATER, T_CTR


def drag_dataset(directory: Path) -> Path:
    """Write a GNS dataset (``train``/``valid``/``test`` npz splits and ``metadata.json``, 2D, 20 steps)
    into ``directory`` (made) and return it: particles under gravity and drag, trajectories of
    different sizes (18 to 40 particles), a sixth of each kinematic (held in place), so that the
    windows of a batch differ in how many particles the loss counts (a rank's loss must be weighed by
    the global batch's particles, not averaged over its own)."""
    from hybridmpm.data import compute_statistics, write_metadata, write_split

    directory.mkdir(parents=True)
    rng = np.random.default_rng(0)
    g = np.array([0.0, -2e-5])
    splits: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {"train": {}, "valid": {}, "test": {}}
    sizes = {"train": [18, 30, 24, 40], "valid": [20], "test": [20]}
    i = 0
    for split, ns in sizes.items():
        for n in ns:
            x = np.empty((21, n, 2))
            x[0] = rng.uniform(0.3, 0.7, (n, 2))
            v = rng.normal(0, 3e-3, (n, 2))
            ptype = np.full(n, GNS_WATER, np.int64)
            ptype[: n // 6] = GNS_KINEMATIC  # held in place
            v[ptype == GNS_KINEMATIC] = 0.0
            for t in range(20):
                v = np.where((ptype == GNS_KINEMATIC)[:, None], 0.0, v + g - 0.2 * v)
                x[t + 1] = x[t] + v
            splits[split][f"simulation_trajectory_{i:05d}"] = (x.astype(np.float32), ptype)
            i += 1
    for split, trajs in splits.items():
        write_split(directory / f"{split}.npz", trajs)
    stats = compute_statistics(splits["train"], exclude_types=(GNS_KINEMATIC,))
    meta = {"bounds": [[0.02, 0.98]] * 2, "sequence_length": 20, "default_connectivity_radius": 0.06, "dim": 2, "dt": 2.5e-3, "r_t": 1, "n_grid": 64}
    write_metadata(directory / "metadata.json", {**meta, **stats})
    return directory


def control_cases(root: Path, cases: int = 4, n: int = 24) -> Path:
    """Write ``cases`` synthetic control cases of water2d (``n`` particles each) under
    ``root/water2d`` in the case-file layout (hybridmpm.train.control.cases) and return ``root``: a
    blob pushed along a straight path, its free motion a fall; arrows and ovals in turn."""
    from hybridmpm.control.sketch import sketch_from_trajectory

    rng = np.random.default_rng(1)
    (root / "water2d").mkdir(parents=True)
    s = np.linspace(0.0, 1.0, T_CTR)[:, None, None]
    for seed in range(cases):
        x0 = rng.uniform(0.35, 0.5, (n, 2))
        shift = rng.uniform(-0.15, 0.15, 2)
        path = x0[None] + s * shift + rng.normal(0, 1e-3, (T_CTR, n, 2))
        free = x0[None] - 0.1 * s**2 * np.array([0.0, 1.0])
        sketch = sketch_from_trajectory(path[0], path[-1], "arrow" if seed % 2 == 0 else "oval")
        arrays = {
            "positions": path[0], "velocities": rng.normal(0, 0.1, (n, 2)), "target": path[-1],
            "tracking": np.zeros((0, n, 2)), "kinematic": np.zeros((T_CTR - 1, n, 2)), "path": path, "free_path": free,
        }  # fmt: skip
        info = {"scene": "water2d", "seed": seed, "kind": "arrow", "preroll": 20, "r_p": 0.5714, "dt_frame": 2.5e-3}
        np.savez(
            root / "water2d" / f"case_{seed:05d}.npz",
            **{k: np.asarray(v, np.float32) for k, v in arrays.items()},
            particle_type=np.full(n, GNS_WATER, np.int64),
            gravity=np.array([0.0, -9.8], np.float32),
            sketch=np.array(json.dumps(sketch.to_json())),
            info=np.array(json.dumps(info)),
        )
    return root


def gns_config(data: Path, out: Path, **kw: Any) -> Any:
    """A tiny GNS training configuration (``hybridmpm.train.gns.train.TrainConfig``: latent 8, one
    layer, 50 steps) on the dataset at ``data``, writing to ``out``; ``kw`` overrides any field.
    Needs the 'train' extra (torch)."""
    from hybridmpm.train.gns.train import TrainConfig

    base = dict(
        scene="drag", data=str(data), out=str(out), latent=8, layers=1, r_t=1, steps=50, lr=3e-3, lr_final=3e-4, noise_std=3e-4,
        val_every=50, val_windows=2, rollout_steps=3, threads=1, snapshots=False, pushforward=0.3, pushforward_after=0.5,
    )  # fmt: skip
    return TrainConfig(**{**base, **kw})
