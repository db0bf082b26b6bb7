#!/usr/bin/env bash
# What curve.sh and recipe.sh do before training, in one place: make the cm2-v2 data if it
# is missing (data.sh), restore a run's committed state into its run folder if that folder
# holds none, then train on the data, resuming from the latest checkpoint when there is one.
# Usage (from the repository root): bash training/cm2-v2/resume.sh RUN STATE [svcode train options]
set -euo pipefail
run="$1" state="$2"
shift 2
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}" OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"
here="$(cd "$(dirname "$0")" && pwd)"
bash "$here/data.sh"
if [ ! -f "$run/checkpoints/latest.json" ] && [ -f "$state/checkpoints/latest.json" ]; then
  mkdir -p "$run" && cp -r "$state/." "$run/"
fi
resume=()
[ -f "$run/checkpoints/latest.json" ] && resume=(--resume)
svcode train --data runs/data-cm2-v2 --out "$run" "$@" --no-progress "${resume[@]}"
