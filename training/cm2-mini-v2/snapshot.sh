#!/usr/bin/env bash
# Copy a training run's resume state into the repository: the latest epoch's checkpoint
# (model, optimiser, schedule, random state), best.safetensors and the logs, with their
# modification times. With a third argument `running` (a run still going, kept only to
# be resumed), best.safetensors is left out when the best epoch is the checkpoint's: its
# weights are the checkpoint's, and a resume writes it again from them.
# Usage (from the repository root): bash training/cm2-mini-v2/snapshot.sh RUN DEST [running]
#   e.g. bash training/cm2-mini-v2/snapshot.sh runs/v2 training/cm2-mini-v2/run
set -euo pipefail
run="$1" dest="$2" mode="${3:-}"
stem="$(python -c 'import json,sys; print(json.load(open(sys.argv[1]))["state"])' \
  "$run/checkpoints/latest.json")"
stem="${stem%.pt}"
mkdir -p "$dest/checkpoints"
rm -f "$dest"/checkpoints/epoch-*
cp -p "$run/checkpoints/$stem".* "$run/checkpoints/latest.json" "$dest/checkpoints/"
cp -p "$run"/log.csv "$run"/log.json "$dest/"
best="$run/best.safetensors"
if [ "$mode" = running ]; then
  best_epoch="$(python -c 'import json,sys; print(json.load(open(sys.argv[1]))["best"].get("epoch"))' "$run/log.json")"
  latest_epoch="$(python -c 'import json,sys; print(json.load(open(sys.argv[1]))["epoch"])' "$run/checkpoints/latest.json")"
  if [ "$best_epoch" = "$latest_epoch" ]; then
    best="" && rm -f "$dest/best.safetensors"
  fi
fi
[ -n "$best" ] && [ -f "$best" ] && cp -p "$best" "$dest/"
echo "$dest: $stem"
