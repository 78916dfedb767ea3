#!/usr/bin/env bash
# Train the shipped configuration of each scene longer: the size sweep
# (train_models.sh) compares candidates at an equal budget of 4000 steps; the
# chosen configuration is then resumed to STEPS under runs/models/SCENE_long/.
# Two trainings at a time, one torch thread each. Resumable.
#
#   bash benchmarks/train_long.sh water2d sand2d ...
set -euo pipefail
cd "$(dirname "$0")/.."
steps2d=${STEPS:-20000}
steps3d=${STEPS3D:-16000}
one() {
  local scene=$1 cfg radius steps
  case $scene in
    *3d) cfg=L2x16_R15_rt4; radius=0.015; steps=$steps3d ;;
    *) cfg=L2x16_R10_rt4; radius=0.0103; steps=$steps2d ;;
  esac
  local out=runs/models/${scene}_long
  mkdir -p "$out"
  # start from the 4000-step sweep run when there is one
  if [ ! -e "$out/$cfg/checkpoint.pt" ] && [ -e "runs/models/$scene/$cfg/checkpoint.pt" ]; then
    cp -r "runs/models/$scene/$cfg" "$out/"
  fi
  hybridmpm train "$scene" --data "data/${scene}_rp" --out "$out/$cfg" --latent 16 --layers 2 --r-t 4 --radius "$radius" \
    --steps "$steps" --val-every 500 --threads 1 --quiet >> "$out/$cfg.log" 2>&1
  echo "$scene done $(date +%T)"
}
pids=()
for s in "$@"; do
  one "$s" &
  pids+=($!)
  if [ ${#pids[@]} -ge 2 ]; then wait "${pids[0]}"; pids=("${pids[@]:1}"); fi
done
wait
