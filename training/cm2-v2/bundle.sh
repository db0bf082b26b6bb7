#!/usr/bin/env bash
# Make the bundled cm2-v2 model from a checkpoint of the long run, with the inference
# settings measured for it, then benchmark it as the package will run it:
#   1. the channel attention pooled over the training patch (384 px) instead of the whole
#      tile, so that the output does not depend on the tile size the memory budget plans;
#   2. the smallest tile overlap within 0.05 dB of the receptive radius's (tile_overlap.py);
#   3. bf16's loss against float32 on the paper-scale benchmark (precision.py), which
#      --precision auto reads;
#   4. the held-out benchmark (svcode bench --system cm2-v2: matched and realistic; the
#      four other regimes in bench/other-regimes) and the whole frames.
# About 3.5 hours on one thread, most of it LSV-ADMM's rows, which do not depend on the
# model: --keep-baselines reruns only SV-CoDe's rows and keeps the other methods' from the
# committed reports (about 1 hour); LSV-ADMM's row at SV-CoDe's time is read out again at
# the new model's seconds from the trace the report keeps. The model card
# (src/svcode_core/weights/cm2-v2.md) quotes the reports written to training/cm2-v2/bench/.
# Usage (from the repository root): bash training/cm2-v2/bundle.sh [--keep-baselines] [MODEL]
set -euo pipefail
bench_rows=() frame_rows=(admm)
if [[ "${1:-}" == --keep-baselines ]]; then
  bench_rows=(--methods svcode --merge) frame_rows=()
  shift
fi
model="${1:-training/cm2-v2/run/best.safetensors}"
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}" OMP_WAIT_POLICY="${OMP_WAIT_POLICY:-PASSIVE}"
here="$(cd "$(dirname "$0")" && pwd)"
out=src/svcode_core/weights/cm2-v2.safetensors
work=runs/cm2-v2-bundle.safetensors
mkdir -p runs
cp "$model" "$work"
python -c "import sys; from svcode_core.methods.model_file import record_pool_window as r
r(sys.argv[1], 384)" "$work"
python bench/tile_overlap.py --weights "$work" --regimes matched --scenes cells ihc --record \
  --out "$here/bench/tile_overlap"
python bench/precision.py --weights "$work" --system cm2-v2 --record --out "$here/bench/precision"
cp "$work" "$out"
svcode bench --system cm2-v2 "${bench_rows[@]}" --out "$here/bench"
svcode bench --system cm2-v2 --regimes calibration model background low-light \
  "${bench_rows[@]}" --out "$here/bench/other-regimes"
python "$here/whole_frames.py" "$out" "${frame_rows[@]}" --out runs/whole-frames
