#!/usr/bin/env bash
# cm2-mini v3 experiments: fine-tune a v2 model on the v2 data (lr 2e-4, cosine, 3200
# patches per epoch), one arm per question. Resumable over sessions (../resume.sh).
#   context           4 epochs, with the lens context (the demixing stage also sees every
#                     lens's crop one pitch away), the loss as in v2 (SSIM + MSE, weights 1, 1)
#   mse               2 epochs, MSE weight 100 (SSIM barely sees the edge strips' brightness)
#   context-mse       2 epochs, both
#   mse-no-coordgate  the mse arm for the v2 ablations, so that they have the same budget
#   mse-no-pe         as the model they are compared with
#   mse-long          8 more epochs of the mse arm's model (lr 4e-4 after 100 warm-up steps,
#                     MSE weight 100, other patches: seed 2): what a longer schedule buys
#   mse-long2         8 more epochs of mse-long's model (lr 3e-4, seed 3): the same again
#   mse-long3         8 more epochs of mse-long2's model (lr 2e-4, seed 4): and again
#   edge              the mse-long3 arm with the squared error of the sub-view's 16-px edge
#                     strips weighted 4 times: does the outer ring catch up with the centre?
#   ring2, ring4      4 more epochs of edge's model (lr 2e-4, seed 5, edge weight 4) with the
#                     squared error of the outer ring (the benchmark's zone) weighted 2 or 4
#                     times: does the ring close the gap it keeps under haze and few photons?
#   ring2-long        8 more epochs of ring2's model (lr 2e-4, seed 6, the same weights): does
#                     the centre come back while the ring keeps its gain?
#   context-ring      6 more epochs of context-scratch's model (lens context; lr 3e-4 after
#                     100 warm-up steps, seed 7, edge weight 4, ring weight 2): does the model
#                     with the better centre catch up in the ring when the loss asks for it?
#   context-ring4     8 more epochs of context-ring's (bundled) model, lr 2e-4, seed 8, ring
#                     weight 4: does a heavier ring weight close more of its ring gap?
#   isolated          4 more epochs of context-ring's (bundled) model, lr 2e-4, seed 9, ring
#                     weight 2, on the v2 data made with the mixed-isolated phantoms (20 %
#                     of the frames: a few large cells alone in a dark field): do the copies
#                     of bright isolated objects one lens pitch away (ghosts) go?
#   ring4-isolated    4 more epochs of context-ring4's (bundled) model on the mixed-isolated
#                     data, lr 2e-4, seed 10, ring weight 4: both gains in one model?
#   reach2            6 more epochs of context-ring4's (bundled) model with the lens context
#                     reaching two pitches left and right (--lens-context 2; the new crops
#                     start at zero weight), lr 2e-4, seed 11, edge and ring weights 4: does
#                     the edge strips' one clean reading, two pitches beyond the old reach,
#                     win them back?
#   context-ring-no-coordgate, context-ring-no-pe, context-ring4-no-coordgate,
#   context-ring4-no-pe
#                     the two fine-tunings above for the ablations of the lens-context model
#                     (context-scratch.sh no-coordgate|no-pe), so that they have its budget
#   context-ring-reach2, context-ring4-reach2
#                     the same two fine-tunings for the model trained from scratch with the
#                     lens context reaching two pitches (context-scratch.sh reach2)
# The v2 model is ../cm2-mini-v2/run/best.safetensors, its ablations'
# ../cm2-mini-v2/ablations/<name>/best.safetensors.
# Usage (from the repository root): bash training/cm2-mini-v3/finetune.sh ARM
set -euo pipefail
arm="$1"
here="$(cd "$(dirname "$0")" && pwd)"
# context-ring4's best epoch, the bundled cm2-mini model before ../cm2-mini-v5's edge16
ring4_best="$here/context-ring4/best.safetensors"
v2="$here/../cm2-mini-v2"
base="$v2/run/best.safetensors"
# mse-long3 and edge differ only in the edge weight
long3=(--init "$here/mse-long2/best.safetensors" --mse-weight 100 --epochs 8
       --lr 2e-4 --warmup-steps 100 --seed 4)
# the two fine-tunings of the bundled lens-context model (and of its ablations)
ring2=(--lens-context --mse-weight 100 --epochs 6 --lr 3e-4 --warmup-steps 100 --seed 7
       --edge-weight 4 --ring-weight 2)
ring4=(--lens-context --mse-weight 100 --epochs 8 --lr 2e-4 --warmup-steps 100 --seed 8
       --edge-weight 4 --ring-weight 4)
case "$arm" in
  context) extra=(--init "$base" --lens-context --epochs 4);;
  mse) extra=(--init "$base" --mse-weight 100 --epochs 2);;
  context-mse) extra=(--init "$base" --lens-context --mse-weight 100 --epochs 2);;
  mse-no-coordgate|mse-no-pe)
    extra=(--init "$v2/ablations/${arm#mse-}/best.safetensors" --mse-weight 100 --epochs 2);;
  mse-long) extra=(--init "$here/mse/best.safetensors" --mse-weight 100 --epochs 8
                  --lr 4e-4 --warmup-steps 100 --seed 2);;
  mse-long2) extra=(--init "$here/mse-long/best.safetensors" --mse-weight 100 --epochs 8
                   --lr 3e-4 --warmup-steps 100 --seed 3);;
  mse-long3) extra=("${long3[@]}");;
  edge) extra=("${long3[@]}" --edge-weight 4);;
  ring2|ring4) extra=(--init "$here/edge/best.safetensors" --mse-weight 100 --epochs 4
                      --lr 2e-4 --warmup-steps 100 --seed 5 --edge-weight 4
                      --ring-weight "${arm#ring}");;
  ring2-long) extra=(--init "$here/ring2/best.safetensors" --mse-weight 100 --epochs 8
                     --lr 2e-4 --warmup-steps 100 --seed 6 --edge-weight 4 --ring-weight 2);;
  context-ring) extra=(--init "$here/context-scratch/best.safetensors" "${ring2[@]}");;
  context-ring-no-coordgate|context-ring-no-pe)
    extra=(--init "$here/context-scratch-${arm#context-ring-}/best.safetensors" "${ring2[@]}");;
  context-ring4) extra=(--init "$here/context-ring/best.safetensors" "${ring4[@]}");;
  context-ring4-no-coordgate|context-ring4-no-pe)
    extra=(--init "$here/context-ring-${arm#context-ring4-}/best.safetensors" "${ring4[@]}");;
  context-ring-reach2)
    extra=(--init "$here/context-scratch-reach2/best.safetensors" "${ring2[@]}" --lens-context 2);;
  context-ring4-reach2)
    extra=(--init "$here/context-ring-reach2/best.safetensors" "${ring4[@]}" --lens-context 2);;
  isolated) export OBJECTS=mixed-isolated
            extra=(--init "$here/context-ring/best.safetensors" --lens-context
                   --mse-weight 100 --epochs 4 --lr 2e-4 --warmup-steps 100 --seed 9
                   --edge-weight 4 --ring-weight 2);;
  ring4-isolated) export OBJECTS=mixed-isolated
                  extra=(--init "$ring4_best" --lens-context
                         --mse-weight 100 --epochs 4 --lr 2e-4 --warmup-steps 100 --seed 10
                         --edge-weight 4 --ring-weight 4);;
  reach2) extra=(--init "$ring4_best" "${ring4[@]}" --epochs 6
                  --seed 11 --lens-context 2);;
  *) echo "finetune: context, mse, context-mse, mse-no-coordgate, mse-no-pe, mse-long, mse-long2, mse-long3, edge, ring2, ring4, ring2-long, context-ring, context-ring4, isolated, ring4-isolated, reach2 or context-ring[4]-no-coordgate|no-pe|reach2" >&2
     exit 2;;
esac
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
# the arm's options come last: they override these
bash "$here/../resume.sh" "runs/v3-$arm" "$here/$arm" \
  --batch-size 8 --same-origin 8 --lr 2e-4 --warmup-steps 50 \
  --patches-per-epoch 3200 --val-patches 128 --seed 1 "${extra[@]}"
