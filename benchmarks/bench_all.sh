#!/usr/bin/env bash
# The charts and tables of docs/benchmarks.md: `hybridmpm bench` on
# every 2D scene, water3d and sand3d, 3 held-out seeds (1000-1002), the paper's T
# frames, MPM on all cores, onnxruntime on one thread; Taichi as the MPM peer
# (needs `pip install -e '.[bench]'`; PEER= to skip). Resumable (finished
# cells are kept in benchmarks/results/bench/SCENE/cells, not in git).
#
#   bash benchmarks/bench_all.sh                 # all scenes
#   bash benchmarks/bench_all.sh water2d sand2d  # some
set -euo pipefail
cd "$(dirname "$0")/.."
peer=${PEER-taichi}
scenes=("$@")
[ ${#scenes[@]} -gt 0 ] || scenes=(water2d sand2d water_ramps2d sand_ramps2d water_sand2d dam_break2d water3d sand3d)
for s in "${scenes[@]}"; do
  seeds=3
  [ "$s" = dam_break2d ] && seeds=1  # deterministic: every seed is the same column
  if [ "$peer" = taichi ]; then  # first, so that bench writes its line into report.md
    python benchmarks/taichi_peer.py --bench-scene "$s" --bench-out "benchmarks/results/bench/$s"
  fi
  hybridmpm bench "$s" --seeds $seeds --out "benchmarks/results/bench/$s"
done
python benchmarks/bench_summary.py benchmarks/results/bench --out benchmarks/results/bench/summary.md
