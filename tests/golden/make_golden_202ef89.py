"""Record the trajectories of main at 202ef89 (before the simulator interface) as hashes.

Run once against a checkout of 202ef89 (its package on PYTHONPATH, its Rust
extension built), e.g.::

    git worktree add /tmp/old 202ef89 && (cd /tmp/old && maturin build --release -o /tmp/w)
    # unzip the wheel's _core*.so into /tmp/old/python/hybridmpm/
    PYTHONPATH=/tmp/old/python python tests/golden/make_golden_202ef89.py > tests/golden/golden_202ef89.json

It uses only the 202ef89 API (``Scene.make_solver().step_frame``, ``run_neural``,
``HybridSimulator.step``). ``tests/test_golden.py`` replays the same runs through
:mod:`hybridmpm.sim` and requires identical bytes.
"""

from __future__ import annotations

import hashlib
import json
import sys

import numpy as np

SCENES = ("water2d", "sand2d", "water_ramps2d", "sand_ramps2d", "water_sand2d", "water3d", "sand3d", "dam_break2d")
SEEDS = (0, 1000)
MPM_FRAMES = 50
NN_SCENES = ("water2d", "dam_break2d")
NN_FRAMES = 120


def digest(x: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(x, np.float32).tobytes()).hexdigest()


def main() -> None:
    import hybridmpm
    from hybridmpm.hybrid import HybridSimulator
    from hybridmpm.models import shipped_model
    from hybridmpm.neural import NeuralModel
    from hybridmpm.neural.runtime import run_neural
    from hybridmpm.scenes import make_scene

    out: dict = {"source": "main at 202ef89", "numpy": np.__version__, "mpm": {}, "neural": {}, "hybrid": {}}
    for name in SCENES:
        for seed in SEEDS:
            scene = make_scene(name, seed=seed)
            sim = scene.make_solver(num_threads=0)
            pos = [np.asarray(sim.positions, np.float32).copy()]
            for _ in range(MPM_FRAMES):
                sim.step_frame(scene.dt_frame)
                pos.append(np.asarray(sim.positions, np.float32).copy())
            p = np.stack(pos)
            out["mpm"][f"{name}/{seed}"] = {"sha256": digest(p), "shape": list(p.shape), "sum": float(p.astype(np.float64).sum())}
            print(name, seed, "mpm", file=sys.stderr)
    for name in NN_SCENES:
        for seed in SEEDS:
            scene = make_scene(name, seed=seed)
            model = NeuralModel(shipped_model(name))
            res = run_neural(scene, model, NN_FRAMES, seed=seed)
            p = res["positions"]
            out["neural"][f"{name}/{seed}"] = {"sha256": digest(p), "shape": list(p.shape), "sum": float(p.astype(np.float64).sum())}
            sim = HybridSimulator(make_scene(name, seed=seed), None, seed=seed)
            frames = [sim.initial_frame()] + list(sim.step(NN_FRAMES))
            p = np.stack([f.positions for f in frames])
            out["hybrid"][f"{name}/{seed}"] = {
                "sha256": digest(p),
                "shape": list(p.shape),
                "sum": float(p.astype(np.float64).sum()),
                "solver": "".join("n" if f.solver == "neural" else "m" for f in frames),
                "events": [[f.step, f.event] for f in frames if f.event],
            }
            print(name, seed, "nn/hybrid", out["hybrid"][f"{name}/{seed}"]["solver"], file=sys.stderr)
    out["hybridmpm"] = hybridmpm.__version__
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
