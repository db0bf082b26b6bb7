#!/usr/bin/env bash
# The cm2-v2 training data: 48 paper-scale frames (43 for training, 5 for validation) of
# mixed phantoms, each through its own draw of the realistic instrument departures (scaled
# to cm2-v2's pixels; a new draw every 8 frames), stored in float16: about 220 MB a frame,
# 10.5 GB in all, about 1 CPU-minute a frame on one thread. Frame i depends only on the
# seed and i; rerunning finishes an interrupted generation.
# Usage (from the repository root): bash training/cm2-v2/data.sh [OUT]
set -euo pipefail
export OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"
svcode dataset --system cm2-v2 --frames 48 --out "${1:-runs/data-cm2-v2}" --seed 0 \
  --departures realistic --instrument-frames 8 --dtype float16 --no-progress
