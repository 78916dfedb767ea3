#!/usr/bin/env bash
# Stress suite on the 2D scenes (issue 5): neural-only, MPM-only and hybrid
# through baseline / fast / obstacle / dense cases, 1000-frame rollouts.
# Tables: benchmarks/results/stress/stress_SCENE.md (collected in docs/stability.md).
set -euo pipefail
cd "$(dirname "$0")/.."
for s in ${SCENES:-water2d sand2d water_ramps2d sand_ramps2d water_sand2d}; do
  hybridmpm stress "$s" --frames "${FRAMES:-1000}" --seed "${SEED:-1000}" --out benchmarks/results/stress --quiet
done
