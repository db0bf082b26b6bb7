#!/usr/bin/env bash
# One arm of the cm2-v2 learning curve: SV-CoDe with lens context, the network of ARM.json
# (depth4: demixing 4 levels, reconstruction 3, the mini model's widths, receptive radius
# 118 px; depth5: 5 and 4 levels, 238 px; depth5-w64: the same with no level wider than 64
# channels; depth5-f2: those levels on a grid twice coarser, 32 channels first, 478 px;
# depth4-f4: 4 and 3 levels on a grid four times coarser, 64 channels, 478 px; the cm2-v2
# PSF's support is 129 px), trained on P-pixel patches of the cm2-v2 data (data.sh) in
# bf16, with the exposure brought to one level as at reconstruction: 100 steps of 4
# patches (one origin) an epoch, validation on 32 fixed patches after each (the 384-px
# arms appended --batch-size 1 --same-origin 1 --patches-per-epoch 100 --val-patches 8).
# Resumable: the run folder is runs/cm2-v2-ARM-pP, its kept state ./curve/ARM-pP.
# Usage (from the repository root): bash training/cm2-v2/curve.sh ARM P [options]
set -euo pipefail
depth="${1:-}" patch="${2:-}"
case "$depth" in depth4|depth5|depth5-w64|depth5-f2|depth4-f4) ;;
  *) echo "curve: depth4, depth5, depth5-w64, depth5-f2 or depth4-f4, then P" >&2; exit 2;; esac
[ -n "$patch" ] || { echo "curve: give the patch side P" >&2; exit 2; }
shift 2
here="$(cd "$(dirname "$0")" && pwd)"
bash "$here/resume.sh" "runs/cm2-v2-$depth-p$patch" "$here/curve/$depth-p$patch" \
  --model-config "$here/$depth.json" \
  --lens-context --patch-size "$patch" --precision bf16 --normalise-exposure \
  --mse-weight 100 --epochs 10 --batch-size 4 --same-origin 4 --patches-per-epoch 400 \
  --val-patches 32 --lr 8e-4 --warmup-steps 100 --seed 0 "$@"
