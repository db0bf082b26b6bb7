#!/usr/bin/env bash
# Copy a training run's resume state into the repository: the latest epoch's checkpoint
# (model, optimiser, schedule, random state), best.safetensors and the logs, with their
# modification times.
# Usage (from the repository root): bash training/cm2-mini-v2/snapshot.sh RUN DEST
#   e.g. bash training/cm2-mini-v2/snapshot.sh runs/v2 training/cm2-mini-v2/run
set -euo pipefail
run="$1" dest="$2"
stem="$(python -c 'import json,sys; print(json.load(open(sys.argv[1]))["state"])' \
  "$run/checkpoints/latest.json")"
stem="${stem%.pt}"
mkdir -p "$dest/checkpoints"
rm -f "$dest"/checkpoints/epoch-*
cp -p "$run/checkpoints/$stem".* "$run/checkpoints/latest.json" "$dest/checkpoints/"
cp -p "$run"/log.csv "$run"/log.json "$dest/"
[ -f "$run/best.safetensors" ] && cp -p "$run/best.safetensors" "$dest/"
echo "$dest: $stem"
