#!/usr/bin/env bash
# cm2-mini v3: the v2 recipe from scratch with the lens context and MSE weight 100, to find
# out whether a model that has the neighbouring lenses' crops from its first step uses them
# for the edge strips (fine-tuned from the v2 model, it did not). About 6 CPU-hours on one
# thread, resumable over sessions. With an ablation (no-coordgate or no-pe) the same recipe
# with the coordinate gate or the positional encoding switched off, in its own run and
# state folders (context-scratch-ABLATION): the ablations of the lens-context model. With
# reach2 the same recipe with the lens context reaching two pitches left and right
# (--lens-context 2), in context-scratch-reach2: does a model that has the edge strips'
# one clean reading from its first step win them back?
# Usage (from the repository root): bash training/cm2-mini-v3/context-scratch.sh [VARIANT]
set -euo pipefail
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
here="$(cd "$(dirname "$0")" && pwd)"
name=context-scratch variant=()
case "${1:-}" in
  "") ;;
  no-coordgate|no-pe) name="context-scratch-$1" variant=(--ablation "$1");;
  reach2) name="context-scratch-$1" variant=(--lens-context 2);;
  *) echo "context-scratch: no variant, no-coordgate, no-pe or reach2" >&2; exit 2;;
esac
bash "$here/../cm2-mini-v2/recipe.sh" "runs/v3-$name" "$here/$name" \
  --lens-context --mse-weight 100 "${variant[@]}"
