#!/usr/bin/env bash
# Fill bench/gpu-wheels/ (ignored by git) with the wheels bench/gpu_check.sh installs on a
# GPU machine without network. That machine has torch, numpy, scipy, scikit-image, tifffile,
# safetensors and pytest; of the core's other dependencies only these are imported on the
# check's paths: tqdm (svcode simulate and reconstruct) and pytorch-msssim (the training
# loss). matplotlib (figures, loss plots) and distributed (dask: --workers, --scheduler)
# are not. Both wheels are pure Python, so any Python 3 takes them; --no-deps keeps
# pytorch-msssim from pulling torch. The versions are those of the development
# environment.
#
# Usage: bash bench/gpu_wheels.sh   (needs pip and the package index)
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-$(command -v python || command -v python3)}
dest=bench/gpu-wheels
mkdir -p "$dest"
"$PYTHON" -m pip download --quiet --no-deps --only-binary=:all: --dest "$dest" \
    "tqdm==4.70.1" "pytorch-msssim==1.0.0"
for wheel in "$dest"/*.whl; do
    case "$wheel" in
        *-none-any.whl) ;;
        *) echo "not a pure-Python wheel: $wheel" >&2; exit 1 ;;
    esac
done
ls -l "$dest"
du -sh "$dest"
