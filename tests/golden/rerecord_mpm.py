"""Re-record the MPM golden digests of scenes whose numerics changed on purpose.

    python tests/golden/rerecord_mpm.py --reason "..." KEY [KEY ...]

KEY is ``scene/seed`` as in ``golden_202ef89.json``. Each run is the one
``tests/test_golden.py`` makes (``rollout(MpmSimulator(make_scene(scene,
seed)), 50)``); its digest, shape and coordinate sum go to
``golden_mpm_rerecorded.json`` with the commit and the reason. The test then
checks the key against that digest, and its coordinate sum against the
202ef89 recording within a tolerance (the change must stay a rounding-level one).
"""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path

import numpy as np

from hybridmpm.bench.env import git_commit
from hybridmpm.scenes import make_scene
from hybridmpm.sim import MpmSimulator, rollout

HERE = Path(__file__).parent
OUT = HERE / "golden_mpm_rerecorded.json"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("keys", nargs="+")
    ap.add_argument("--reason", required=True)
    args = ap.parse_args()
    golden = json.loads((HERE / "golden_202ef89.json").read_text())["mpm"]
    out = json.loads(OUT.read_text()) if OUT.exists() else {}
    for key in args.keys:
        if key not in golden:
            raise SystemExit(f"{key}: not a key of golden_202ef89.json")
        name, seed = key.split("/")
        pos = rollout(MpmSimulator(make_scene(name, seed=int(seed)), threads=0), 50).fluid_positions
        out[key] = {
            "sha256": hashlib.sha256(np.ascontiguousarray(pos, np.float32).tobytes()).hexdigest(),
            "shape": list(pos.shape),
            "sum": float(pos.astype(np.float64).sum()),
            "commit": git_commit(),
            "reason": args.reason,
        }
        print(key, out[key]["sum"], "202ef89:", golden[key]["sum"])
    OUT.write_text(json.dumps(out, indent=1, sort_keys=True) + "\n")


if __name__ == "__main__":
    main()
