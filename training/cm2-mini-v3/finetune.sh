#!/usr/bin/env bash
# cm2-mini v3 experiment: fine-tune the bundled v2 model on the v2 data, with the lens
# context (the demixing stage also sees every lens's crop one pitch away) or without it
# (the control: what fine-tuning alone changes). Resumable over sessions.
# Usage (from the repository root): bash training/cm2-mini-v3/finetune.sh context|control
set -euo pipefail
arm="$1"
case "$arm" in context) extra=(--lens-context);; control) extra=();;
  *) echo "finetune: context or control" >&2; exit 2;; esac
export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}" OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
here="$(cd "$(dirname "$0")" && pwd)"
out="runs/v3-$arm"
svcode dataset --preset cm2-mini --frames 480 --out runs/data-v2 --seed 0 \
  --departures "$here/../cm2-mini-v2/departures.json" --no-progress
if [ ! -f "$out/checkpoints/latest.json" ] && [ -f "$here/$arm/checkpoints/latest.json" ]; then
  mkdir -p "$out" && cp -r "$here/$arm/." "$out/"
fi
resume=()
[ -f "$out/checkpoints/latest.json" ] && resume=(--resume)
svcode train --preset cm2-mini --data runs/data-v2 --out "$out" --init pretrained \
  "${extra[@]}" --epochs 4 --batch-size 8 --same-origin 8 --lr 2e-4 --warmup-steps 50 \
  --patches-per-epoch 3200 --val-patches 128 --seed 1 --no-progress "${resume[@]}"
