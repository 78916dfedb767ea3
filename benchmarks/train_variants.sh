#!/usr/bin/env bash
# Train the neural variants that `hybridmpm bench` compares with the shipped
# low-resolution models (paper Fig. 5 a-c):
#   full      r_p = 1,      r_t = 1   every 2D scene (the paper's "original neural physics")
#   spatial   r_p = 0.5714, r_t = 1   water2d only (spatial-only reduction)
#   temporal  r_p = 1,      r_t = 4   water2d only (temporal-only reduction)
# Same network as the shipped models (latent 16, L = 2, 4000 steps, one torch
# thread, two trainings at a time). The connectivity radius is scaled with the
# particle spacing so every variant sees the same ~neighbour count:
# R = 0.0103 m at r_p = 0.5714, 0.0103·sqrt(0.5714) = 0.0078 m at r_p = 1.
# Full-resolution data: 40 trajectories per scene (32/4/4). Resumable: generate
# and train both continue where they stopped.
#
#   bash benchmarks/train_variants.sh water2d sand2d water_ramps2d sand_ramps2d water_sand2d
set -euo pipefail
cd "$(dirname "$0")/.."
steps=${STEPS:-4000}
for s in "$@"; do
  [ -e "data/${s}_full/metadata.json" ] || hybridmpm generate "$s" --trajectories 40 --r-p 1 --workers 2 --quiet --out "data/${s}_full"
done
train() {  # scene data out r_t radius
  mkdir -p "$(dirname "$3")"
  hybridmpm train "$1" --data "$2" --out "$3" --latent 16 --layers 2 --r-t "$4" --radius "$5" \
    --steps "$steps" --val-every 500 --threads 1 --quiet >> "$3.log" 2>&1
  echo "$3 done $(date +%T)"
}
jobs=()
for s in "$@"; do
  jobs+=("$s data/${s}_full runs/models/variants/$s/full_L2x16_R078_rt1 1 0.0078")
  if [ "$s" = water2d ]; then
    jobs+=("$s data/${s}_rp runs/models/variants/$s/spatial_L2x16_R10_rt1 1 0.0103")
    jobs+=("$s data/${s}_full runs/models/variants/$s/temporal_L2x16_R078_rt4 4 0.0078")
  fi
done
i=0
while [ $i -lt ${#jobs[@]} ]; do
  # shellcheck disable=SC2086
  train ${jobs[$i]} &
  if [ $((i + 1)) -lt ${#jobs[@]} ]; then train ${jobs[$((i + 1))]} & fi
  wait
  i=$((i + 2))
done
