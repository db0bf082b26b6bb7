#!/usr/bin/env bash
# The prepared GPU check (issue 48): CUDA tests, SV-CoDe, LSV-ADMM and the learned baselines
# at paper scale, training throughput; one report, bench/results/gpu.md. Under 8 minutes on
# one H100/H200: bench/gpu_check.py works within --budget (default 400 s) and is stopped at
# GPU_CHECK_LIMIT seconds (default 450) in any case, its report written section by section.
# Without CUDA it checks that every CUDA code path refuses cleanly instead.
#
# The GPU machine has no network: bench/gpu_env.sh runs the code from src/ and installs the
# few pure-Python packages it may lack from bench/gpu-wheels/ (fill it beforehand with bash
# bench/gpu_wheels.sh; the folder is ignored by git, so carry it along).
#
# Usage: bash bench/gpu_check.sh [bench/gpu_check.py options, e.g. --out "$OUT/gpu.md"]
set -uo pipefail
cd "$(dirname "$0")/.."
source bench/gpu_env.sh

command -v nvidia-smi >/dev/null && nvidia-smi -L
"$PYTHON" -c 'import torch; print("torch", torch.__version__, "| CUDA available:",
torch.cuda.is_available(), "|", torch.cuda.get_device_name(0) if torch.cuda.is_available()
else "no GPU")'

limit=${GPU_CHECK_LIMIT:-450}
if command -v timeout >/dev/null; then
    timeout --signal=INT --kill-after=15 "$limit" "$PYTHON" bench/gpu_check.py "$@"
else
    "$PYTHON" bench/gpu_check.py "$@"
fi
status=$?
[ "$status" -eq 124 ] && echo "stopped after $limit s (GPU_CHECK_LIMIT); the report holds the sections done"
exit "$status"
