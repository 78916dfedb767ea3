#!/usr/bin/env bash
# Train the neural-simulator candidates ("model no more than a scene needs").
# Two trainings at a time, one torch thread each (2-core machine). Resumable:
# rerunning continues from each run's checkpoint.pt.
#
#   bash benchmarks/train_models.sh water2d   # needs data/water2d_rp (see below)
#
# Data (r_p = 1/1.75, every frame stored; the model's r_t is chosen at training):
#   hybridmpm generate water2d --trajectories 100 --r-p 0.5714 --out data/water2d_rp
set -euo pipefail
cd "$(dirname "$0")/.."
scene=${1:?scene}
steps=${STEPS:-8000}
data=${DATA:-data/${scene}_rp}
out=${OUT:-runs/models/$scene}
run() {  # name latent layers r_t radius
  hybridmpm train "$scene" --data "$data" --out "$out/$1" --latent "$2" --layers "$3" --r-t "$4" --radius "$5" \
    --steps "$steps" --val-every 500 --threads 1 --quiet > "$out/$1.log" 2>&1
}
mkdir -p "$out"
run L2x16_R15_rt2 16 2 2 0.015 & run L2x16_R10_rt2 16 2 2 0.0103 & wait
run L2x16_R10_rt4 16 2 4 0.0103 & run L3x32_R15_rt2 32 3 2 0.015 & wait
