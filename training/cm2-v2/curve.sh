#!/usr/bin/env bash
# One arm of the cm2-v2 learning curve: SV-CoDe with lens context, the bundled mini
# model's widths at one of two depths (depth4.json: demixing 4 levels, reconstruction 3,
# receptive radius 118 px; depth5.json: 5 and 4, 238 px; depth5-w64.json: the same with no
# level wider than 64 channels, a sixth of its parameters; depth5-f2.json: the same levels
# on a grid twice coarser, pixel_unshuffle 2, 32 channels at its first level, 478 px;
# depth4-f4.json: 4 and 3 levels on a grid four times coarser, 64 channels at every
# level, 478 px; the cm2-v2 PSF's support is 129 px), trained on P-pixel patches of the cm2-v2 data (data.sh) in bf16, with the
# exposure brought to one level as at reconstruction. 100 steps of 4 patches (one origin)
# an epoch, validation on 32 fixed patches after each. Resumable: the run folder is
# runs/cm2-v2-DEPTH-pP, its kept state ./curve/DEPTH-pP.
# Usage (from the repository root): bash training/cm2-v2/curve.sh depth4|depth5|depth5-w64|depth5-f2|depth4-f4 P
set -euo pipefail
depth="${1:-}" patch="${2:-}"
case "$depth" in depth4|depth5|depth5-w64|depth5-f2|depth4-f4) ;;
  *) echo "curve: depth4, depth5, depth5-w64, depth5-f2 or depth4-f4, then P" >&2; exit 2;; esac
[ -n "$patch" ] || { echo "curve: give the patch side P" >&2; exit 2; }
shift 2
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}" OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"
here="$(cd "$(dirname "$0")" && pwd)"
run="runs/cm2-v2-$depth-p$patch" state="$here/curve/$depth-p$patch"
bash "$here/data.sh"
if [ ! -f "$run/checkpoints/latest.json" ] && [ -f "$state/checkpoints/latest.json" ]; then
  mkdir -p "$run" && cp -r "$state/." "$run/"
fi
resume=()
[ -f "$run/checkpoints/latest.json" ] && resume=(--resume)
svcode train --data runs/data-cm2-v2 --out "$run" --model-config "$here/$depth.json" \
  --lens-context --patch-size "$patch" --precision bf16 --normalise-exposure \
  --mse-weight 100 --epochs 10 --batch-size 4 --same-origin 4 --patches-per-epoch 400 \
  --val-patches 32 --lr 8e-4 --warmup-steps 100 --seed 0 --no-progress "${resume[@]}" "$@"
