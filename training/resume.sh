#!/usr/bin/env bash
# What every cm2-mini recipe here does before training, in one place: regenerate the v2
# data if it is missing (frame i depends only on the seed and i: the same 480 frames every
# time, about 1 CPU-second each), restore a run's committed state into its run folder if
# that folder holds none, then train, resuming from the latest checkpoint when there is one.
# Usage (from the repository root): bash training/resume.sh RUN STATE [svcode train options]
# OBJECTS=KIND (default mixed) trains on the v2 data with another phantom kind instead,
# in runs/data-v2-KIND (the same seed, departures and frame count). MARGIN=PX stores the
# views and targets PX past each sub-view's window (runs/data-v2-mPX, about 1.2 x the disk):
# the model is then trained with that view margin. DEPARTURES=FILE draws the instruments
# from FILE instead of cm2-mini-v2/departures.json, in a data folder named after it.
set -euo pipefail
run="$1" state="$2"
shift 2
here="$(cd "$(dirname "$0")" && pwd)"
# Threads that wait sleep instead of spinning: on a shared machine spinning cost a run up
# to twice the CPU time per epoch.
export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"
objects="${OBJECTS:-mixed}"
data=runs/data-v2
[ "$objects" = mixed ] || data="runs/data-v2-$objects"
margin="${MARGIN:-0}"
[ "$margin" = 0 ] || data="$data-m$margin"
departures="${DEPARTURES:-$here/cm2-mini-v2/departures.json}"
[ -z "${DEPARTURES:-}" ] || data="$data-$(basename "$departures" .json)"
svcode dataset --preset cm2-mini --frames 480 --out "$data" --seed 0 --objects "$objects" \
  --departures "$departures" --view-margin "$margin" --no-progress
if [ ! -f "$run/checkpoints/latest.json" ] && [ -f "$state/checkpoints/latest.json" ]; then
  mkdir -p "$run" && cp -r "$state/." "$run/"
fi
resume=()
[ -f "$run/checkpoints/latest.json" ] && resume=(--resume)
svcode train --preset cm2-mini --data "$data" --out "$run" "$@" --no-progress "${resume[@]}"
