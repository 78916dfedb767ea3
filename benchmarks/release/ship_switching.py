"""Choose each scene's switching rule for the shipped model and write
``python/hybridmpm/models/switching.json`` (docs/hybrid.md "Switching rules").

    python benchmarks/release/ship_switching.py benchmarks/results/switching

Reads the ``benchmarks/hybrid_choices.py`` results ``DIR/SCENE.json`` made on
validation seeds (2000-2002, 400 frames) with the variants "defaults" (the
score and the MPM audit), "rule error" (1 g), "rule error, tol 2 g" and
"rule error, tol 3 g". Rule: among those whose mean grid-mass error is no
higher than the defaults', the one that gives the network the most frames
(ties: the lower error). A scene whose choice is the defaults gets no entry.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from hybridmpm.bench.harness import read_results, write_json
from hybridmpm.models import shipped_models

MODELS = Path(__file__).resolve().parents[2] / "python" / "hybridmpm" / "models"
#: hybrid_choices label -> the hybrid's switching settings.
CANDIDATES = {
    "defaults": {"safeguard": "audit"},
    "rule error": {"safeguard": "error", "audit_tol": 1.0},
    "rule error, tol 2 g": {"safeguard": "error", "audit_tol": 2.0},
    "rule error, tol 3 g": {"safeguard": "error", "audit_tol": 3.0},
}


def choose(rows: list[dict]) -> tuple[str, dict]:
    """(label, row) of the chosen variant among ``rows`` (hybrid_choices records)."""
    by = {r["variant"]: r for r in rows if r["variant"] in CANDIDATES}
    if "defaults" not in by:
        raise SystemExit("results: no 'defaults' row")
    limit = by["defaults"]["error_mean"]
    ok = [(label, r) for label, r in by.items() if r["error_mean"] <= limit]
    return min(ok, key=lambda lr: (lr[1]["mpm_share"], lr[1]["error_mean"]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("results", type=Path, help="directory of hybrid_choices SCENE.json files")
    args = ap.parse_args(argv)
    out = {}
    for path in sorted(args.results.glob("*.json")):
        scene = path.stem
        if scene not in shipped_models():
            continue  # other measurements kept beside them
        rows = read_results(path)["rows"]
        label, row = choose(rows)
        d = next(r for r in rows if r["variant"] == "defaults")
        print(
            f"{scene}: {label} (error {row['error_mean']:.3f}, network {100 * (1 - row['mpm_share']):.0f}%; defaults {d['error_mean']:.3f}, {100 * (1 - d['mpm_share']):.0f}%)"
        )
        if label != "defaults":
            out[scene] = {
                **CANDIDATES[label],
                "validation": {"seeds": "2000-2002", "frames": 400, "error_mean": round(row["error_mean"], 4), "network_share": round(1 - row["mpm_share"], 3),
                               "defaults_error_mean": round(d["error_mean"], 4), "defaults_network_share": round(1 - d["mpm_share"], 3)},
            }  # fmt: skip
    write_json(MODELS / "switching.json", out, indent=2, sort_keys=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
