#!/usr/bin/env bash
# cm2-mini v3: the v2 recipe from scratch with the lens context and MSE weight 100, to find
# out whether a model that has the neighbouring lenses' crops from its first step uses them
# for the edge strips (fine-tuned from the v2 model, it did not). About 6 CPU-hours on one
# thread, resumable over sessions.
# Usage (from the repository root): bash training/cm2-mini-v3/context-scratch.sh
set -euo pipefail
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
here="$(cd "$(dirname "$0")" && pwd)"
bash "$here/../cm2-mini-v2/recipe.sh" runs/v3-context-scratch "$here/context-scratch" \
  --lens-context --mse-weight 100
