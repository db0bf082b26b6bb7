#!/usr/bin/env bash
# Four more epochs of v3's context-ring4 model (bundled before edge16; the recipe of its
# last fine-tuning: lr 2e-4, MSE weight 100, edge and ring weights 4, seed 12), one arm
# per question:
#   zeros     as the model is (zero padding): the control
#   reflect   every padded convolution of both stages mirrors (--padding reflect): does
#             mirrored padding win the border back for the whole model?
#   edge16    the edge strips' squared error weighted 16 times instead of 4: do the
#             strips follow their weight in the loss?
#   edge16-long  4 more epochs of edge16's model (seed 13, the same weights): do they go on?
#   edge32-ring8 4 more epochs of edge16's model (seed 13) with the strips weighted 32 and
#             the outer ring 8: does the ring keep up when both weights rise?
#   partial4  every pixel that some lens loses off the sensor weighted 4 (the rows within
#             96 px of the top and bottom as well as the column strips, which with the
#             edge weight come to 16, as in edge16): do those rows keep their level while
#             the strips gain?
#   margin16  edge16-long with each lens view running 16 px (the kernel radius) past its
#             window in both stages and the demixing targets (--view-margin 16): does the
#             light that the window cuts off win the strips back? edge16-long is its control.
#   margin16-long  the same over 8 epochs: does the margin's new region need more?
#   m16-edge32-ring8  4 more epochs of margin16's model (seed 14) with the strips weighted
#             32 and the ring 8: do the weights move the border further once the views run
#             past the window?
#   m16-partial4  4 more epochs of margin16's model (seed 14) with every pixel that some
#             lens loses off the sensor weighted 4 as well
#   h50-margin16  4 more epochs of margin16's model (seed 14, its own weights: strips 16,
#             ring 4) on frames whose haze reaches half the signal (haze50.json; the v2
#             recipe stops at a quarter, the held-out background regime has half): does
#             the wider haze range hold the means under haze?
#   h50-edge32-ring8  m16-edge32-ring8 on the same frames: with the haze covered, do the
#             border weights still cost the realistic mean? (bundled as cm2-mini)
#   h50-long  4 more epochs of h50-edge32-ring8's model (seed 15, the same weights): do the
#             ring and the mean go on together?
#   h50-edge64-ring16  the same with the strips weighted 64 and the ring 16: now that the
#             weights no longer cost the mean, do heavier ones move the border?
#   o150-edge32-ring8  h50-long on frames whose optical departures (array shift and
#             rotation, jitter, aberrations, defocus, depth) reach 1.5x the v2 ranges
#             (optics150.json, haze as haze50.json): the held-out realistic instrument sits
#             at the corner of the v2 ranges, where the ring's PSFs depart most; does
#             covering it narrow the ring's gap there?
# The arms after edge16 start from edge16's best epoch (runs/v5-edge16/best.safetensors:
# `finetune.sh edge16` makes it again) or from margin16's (runs/v5-margin16/best.safetensors:
# `finetune.sh margin16` after edge16; it was the bundled cm2-mini model while the m16 and
# h50 arms ran, and h50-edge32-ring8 is the bundled model now).
# Resumable over sessions (../resume.sh).
# Usage (from the repository root): bash training/cm2-mini-v5/finetune.sh ARM
set -euo pipefail
arm="$1"
here="$(cd "$(dirname "$0")" && pwd)"
edge16=runs/v5-edge16/best.safetensors
margin16=runs/v5-margin16/best.safetensors
h50=runs/v5-h50-edge32-ring8/best.safetensors
case "$arm" in
  h50-long|h50-edge64-ring16|o150-edge32-ring8)
    [ -f "$h50" ] || { echo "finetune.sh $arm starts from $h50: run the h50-edge32-ring8 arm" \
                         "first" >&2; exit 2; };;
  edge16-long|edge32-ring8|margin16|margin16-long)
    [ -f "$edge16" ] || { echo "finetune.sh $arm starts from $edge16: run the edge16 arm first" >&2
                          exit 2; };;
  m16-*|h50-margin16|h50-edge32-ring8)
    [ -f "$margin16" ] || { echo "finetune.sh $arm starts from $margin16: run the margin16 arm" \
                              "first" >&2; exit 2; };;
esac
case "$arm" in
  zeros) extra=();;
  reflect) extra=(--padding reflect);;
  edge16) extra=(--edge-weight 16);;
  edge16-long) extra=(--edge-weight 16 --seed 13 --init "$edge16");;
  edge32-ring8) extra=(--edge-weight 32 --ring-weight 8 --seed 13 --init "$edge16");;
  partial4) extra=(--partial-weight 4);;
  margin16) extra=(--edge-weight 16 --seed 13 --init "$edge16"); export MARGIN=16;;
  margin16-long) extra=(--edge-weight 16 --seed 13 --init "$edge16" --epochs 8)
    export MARGIN=16;;
  m16-edge32-ring8) extra=(--edge-weight 32 --ring-weight 8 --seed 14 --init "$margin16")
    export MARGIN=16;;
  m16-partial4) extra=(--edge-weight 16 --partial-weight 4 --seed 14 --init "$margin16")
    export MARGIN=16;;
  h50-margin16) extra=(--edge-weight 16 --seed 14 --init "$margin16")
    export MARGIN=16 DEPARTURES="$here/haze50.json";;
  h50-edge32-ring8) extra=(--edge-weight 32 --ring-weight 8 --seed 14 --init "$margin16")
    export MARGIN=16 DEPARTURES="$here/haze50.json";;
  h50-long) extra=(--edge-weight 32 --ring-weight 8 --seed 15 --init "$h50")
    export MARGIN=16 DEPARTURES="$here/haze50.json";;
  h50-edge64-ring16) extra=(--edge-weight 64 --ring-weight 16 --seed 15 --init "$h50")
    export MARGIN=16 DEPARTURES="$here/haze50.json";;
  o150-edge32-ring8) extra=(--edge-weight 32 --ring-weight 8 --seed 15 --init "$h50")
    export MARGIN=16 DEPARTURES="$here/optics150.json";;
  *) echo "finetune.sh: zeros, reflect, edge16, edge16-long, edge32-ring8, partial4," \
       "margin16, margin16-long, m16-edge32-ring8, m16-partial4, h50-margin16," \
       "h50-edge32-ring8, h50-long, h50-edge64-ring16 or o150-edge32-ring8" >&2
     exit 2;;
esac
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
# the arm's options come last: they override these
bash "$here/../resume.sh" "runs/v5-$arm" "$here/$arm" \
  --init "$here/../cm2-mini-v3/context-ring4/best.safetensors" \
  --batch-size 8 --same-origin 8 --patches-per-epoch 3200 --val-patches 128 \
  --mse-weight 100 --edge-weight 4 --ring-weight 4 --epochs 4 --lr 2e-4 \
  --warmup-steps 100 --seed 12 "${extra[@]}"
