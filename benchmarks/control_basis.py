#!/usr/bin/env python3
"""What the diffusion controller's representation costs, with the truth known
(see docs/control.md):

    python benchmarks/control_basis.py --scenes water2d,sand2d --cases 6 --out benchmarks/results/control_basis

Per held-out case (seeds 4000+, outside the training seeds' range used so far
and the benchmark's 5000+), the final-shape grid-mass error against ``X_1``
of

* the tracking **acceleration field** replayed open loop in MPM, as solved
  and projected on ``K_b`` temporal B-splines (``field K``) — the design that
  diffuses accelerations;
* the true reverse **path** tracked by the controller's tracking law, as it
  is and projected on ``K_b`` path B-splines (``path K``) — the design that
  diffuses plans (the one shipped); with effort (mean ‖a‖/g).

Writes OUT.json and OUT.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from hybridmpm.bench.harness import script_argv, write_results
from hybridmpm.control import Controller, control_episode
from hybridmpm.control.diffusion import expand, path_basis, project, temporal_basis
from hybridmpm.train.control.cases import make_case

KS = (4, 6, 8, 12, 16)


def run(scene: str, seed: int) -> dict:
    case = make_case(scene, seed, "arrow" if seed % 2 == 0 else "oval")
    frames = len(case.tracking)
    row: dict = {"scene": scene, "seed": seed, "kind": case.kind}
    for k in (0, *KS):
        f = case.tracking if k == 0 else expand(project(case.tracking, temporal_basis(frames, k)), temporal_basis(frames, k))
        ep = control_episode(case.simulator(), case.sketch, Controller("oracle", frames=frames, oracle=f), target=case.target)
        row[f"field {k or 'exact'}"] = [ep.metrics["grid_mass_error"], ep.metrics["effort_mean_g"]]
        path = case.path.astype(np.float64)
        if k:
            b = path_basis(len(path), k)
            path = path[0] + expand(project(path - path[0], b), b)
        ep = control_episode(case.simulator(), case.sketch, Controller("oracle", frames=frames, oracle_path=path), target=case.target)
        row[f"path {k or 'exact'}"] = [ep.metrics["grid_mass_error"], ep.metrics["effort_mean_g"]]
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="water2d,sand2d")
    ap.add_argument("--cases", type=int, default=6)
    ap.add_argument("--first-seed", type=int, default=4000)
    ap.add_argument("--out", default="benchmarks/results/control_basis")
    args = ap.parse_args(argv)
    rows = [run(s, args.first_seed + i) for s in args.scenes.split(",") for i in tqdm(range(args.cases), desc=s)]
    out = Path(args.out)
    cols = [k for k in rows[0] if k.startswith(("field", "path"))]
    lines = ["Mean final grid-mass error against X_1 (mean effort, g), true targets replayed:", ""]
    lines += ["| scene | cases | " + " | ".join(cols) + " |", "|---|---|" + "---|" * len(cols)]
    for s in args.scenes.split(","):
        rs = [r for r in rows if r["scene"] == s]
        cells = [f"{np.mean([r[c][0] for r in rs]):.3f} ({np.mean([r[c][1] for r in rs]):.1f})" for c in cols]
        lines.append(f"| {s} | {len(rs)} | " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    write_results(out.parent, out.name, doc={"rows": rows}, markdown=text, argv=script_argv(__file__, argv))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
