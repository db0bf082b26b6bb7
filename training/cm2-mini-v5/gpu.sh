#!/usr/bin/env bash
# Three fine-tuning arms of the bundled cm2-mini model (margin16 when they ran) on one GPU, side by side,
# within a wall-clock budget, beside the prepared GPU check (bench/gpu_check.sh):
#   gpu-long          margin16's recipe (strips weighted 16, ring 4) on four times the
#                     data (1,920 frames), batch 32, lr 1e-4: does more data and more
#                     steps keep the centre and the realistic mean while the border gains?
#   gpu-edge32-ring8  the same with the strips weighted 32 and the ring 8 (the weights that
#                     moved the ring most on the CPU, at a cost to the centre)
#   gpu-edge64-ring16 the strips weighted 64 and the ring 16: how far do the weights move
#                     the border, and at what cost, once data and steps are plentiful?
# A probe on 16 frames checks the training path first and times an epoch (its second, warm
# one; if it fails, the GPU check alone runs). The data are then simulated on the CPU cores
# (svcode dataset --workers) while the GPU check runs, and the arms' epochs are sized to the
# time left, so the cosine schedule ends inside the budget. Each arm's best weights and log.csv land in
# OUT, with the GPU check's report (gpu.md): seven files.
# Runs from the source tree (no install; bench/gpu_env.sh): the machine needs torch, numpy,
# scipy, scikit-image, tifffile, safetensors and matplotlib; tqdm and pytorch-msssim come
# from bench/gpu-wheels/ (bash bench/gpu_wheels.sh).
# Usage (from the repository root): bash training/cm2-mini-v5/gpu.sh OUT SECONDS
# (a smoke test of this script on a CPU: DEVICE=cpu FRAMES=24 PATCHES=64 ... OUT 300)
set -uo pipefail
out="$1" budget="$2"
start=$(date +%s)
left() { echo $((budget - ($(date +%s) - start))); }
mkdir -p "$out"
here="$(cd "$(dirname "$0")" && pwd)"
source bench/gpu_env.sh
export OMP_WAIT_POLICY=PASSIVE
svcode() { "$PYTHON" -m svcode_core.cli "$@"; }
nvidia-smi -L; lscpu | grep -E "^Model name|^CPU\(s\)"
lscpu | grep -o -w -E "amx_bf16|avx512_bf16" | sort -u | tr '\n' ' '; echo

patches=${PATCHES:-3200}
common=(--preset cm2-mini --device "${DEVICE:-cuda}" --view-margin 16 --batch-size 32
        --init src/svcode_core/weights/cm2-mini.safetensors --same-origin 8 --patches-per-epoch "$patches"
        --mse-weight 100 --lr 1e-4 --warmup-steps 50 --seed 15 --loader-workers 4 --no-progress)
# the probe: 16 frames, two short epochs; it checks the training path on this GPU before
# anything else and times an epoch (the same network and patches as the arms)
svcode dataset --preset cm2-mini --frames 16 --out /tmp/probe-data --seed 99 \
  --departures "$here/../cm2-mini-v2/departures.json" --view-margin 16 --no-progress \
  > /tmp/probe.log 2>&1 &&
svcode train "${common[@]}" --data /tmp/probe-data --out /tmp/probe --epochs 2 \
  --patches-per-epoch $((patches / 5)) --val-patches 32 >> /tmp/probe.log 2>&1
probe=$?
tail -4 /tmp/probe.log
if [ "$probe" -ne 0 ]; then
  echo "probe failed at $(( $(date +%s) - start )) s: the GPU check alone"
  GPU_CHECK_LIMIT=$(( $(left) - 10 )) bash bench/gpu_check.sh --budget $(( $(left) - 30 )) \
    --out "$out/gpu.md" > /tmp/gpu_check.log 2>&1
  tail -30 /tmp/gpu_check.log
  exit 1
fi
epoch=$(tail -1 /tmp/probe/log.csv | awk -F, '{print $(NF-1) * 5}')
echo "probe at $(( $(date +%s) - start )) s: $patches patches in about $epoch s"

data=/tmp/data-gpu-m16
cores=$(nproc)
(OMP_NUM_THREADS=1 svcode dataset --preset cm2-mini --frames "${FRAMES:-1920}" --out "$data" --seed 0 \
   --departures "$here/../cm2-mini-v2/departures.json" --view-margin 16 --dtype float16 \
   --workers $((cores > 4 ? cores - 4 : 1)) --no-progress > /tmp/data.log 2>&1) &
data_pid=$!
check=${GPU_CHECK_LIMIT:-200}
GPU_CHECK_LIMIT=$check bash bench/gpu_check.sh --budget $((check - 20)) --out "$out/gpu.md" \
  > /tmp/gpu_check.log 2>&1
echo "gpu check: exit $? at $(( $(date +%s) - start )) s"; tail -25 /tmp/gpu_check.log
wait "$data_pid" || { echo "data generation failed:"; tail -20 /tmp/data.log; exit 1; }
echo "data at $(( $(date +%s) - start )) s: $(tail -1 /tmp/data.log)"
epochs=$("$PYTHON" -c "print(max(1, int(($(left) - 60) / ($epoch * 1.5))))")
echo "$(left) s left: $epochs epochs each (three arms side by side: 1.5 x the probe's)"

arm() {  # name, options
  local name="$1"; shift
  timeout --signal=INT $(( $(left) - 15 )) "$PYTHON" -m svcode_core.cli train "${common[@]}" \
    --data "$data" --val-patches 128 --out "/tmp/$name" --epochs "$epochs" "$@" \
    > "/tmp/$name.log" 2>&1
  echo "$name: exit $?"; grep -v DataLoader "/tmp/$name.log" | tail -4
  cp "/tmp/$name/best.safetensors" "$out/$name.safetensors"
  cp "/tmp/$name/log.csv" "$out/$name.csv"
}
arm gpu-long --edge-weight 16 --ring-weight 4 &
arm gpu-edge32-ring8 --edge-weight 32 --ring-weight 8 &
arm gpu-edge64-ring16 --edge-weight 64 --ring-weight 16 &
wait
echo "done at $(( $(date +%s) - start )) s"
