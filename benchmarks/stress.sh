#!/usr/bin/env bash
# Stress suite: neural-only, MPM-only, and the hybrid with and
# without its MPM audit, through baseline / fast / obstacle / dense cases,
# 1000-frame rollouts, on the 2D and 3D scenes (SCENES overrides the list).
# Tables: benchmarks/results/stress/stress_SCENE.md (collected in docs/stability.md).
set -euo pipefail
cd "$(dirname "$0")/.."
for s in ${SCENES:-water2d sand2d water_ramps2d sand_ramps2d water_sand2d water3d sand3d}; do
  hybridmpm stress "$s" --frames "${FRAMES:-1000}" --seed "${SEED:-1000}" --out benchmarks/results/stress --quiet
done
