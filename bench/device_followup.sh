#!/usr/bin/env bash
# A short follow-up on a GPU machine whose processor has AMX (an H200 host), after
# bench/gpu_check.sh and training/cm2-mini-v5/gpu.sh: each step bounded by `timeout`.
#   1. the CUDA tests (tests/test_cuda.py -m cuda);
#   2. where `svcode train`'s time goes on the GPU: one short epoch under cProfile (the
#      main process's Python functions by own time; waiting for the GPU shows up in
#      whichever call synchronises);
#   3. the network per part on AMX, one thread (bench/network_parts.py);
#   4. start-up and the 6-frame stack against LSV-ADMM's fast point on two cores
#      (bench/results/stack6.md's commands; CPU seconds of the whole process).
# Reports land in OUT. Usage: bash bench/device_followup.sh OUT
set -uo pipefail
out="$1"
mkdir -p "$out"
source bench/gpu_env.sh
export PYTHONPATH="$PWD/bench:$PYTHONPATH"
svcode() { "$PYTHON" -m svcode_core.cli "$@"; }
cpu() {  # CPU seconds (user + system), wall seconds and peak RSS of a command
  "$PYTHON" - "$@" <<'EOF'
import resource, subprocess, sys, time
start = time.perf_counter()
code = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL).returncode
usage = resource.getrusage(resource.RUSAGE_CHILDREN)
print(f"exit {code}: CPU {usage.ru_utime + usage.ru_stime:.2f} s, wall "
      f"{time.perf_counter() - start:.2f} s, peak RSS {usage.ru_maxrss / 1024:.0f} MiB")
EOF
}

echo "== 1. CUDA tests"
timeout 90 "$PYTHON" -m pytest -m cuda -q -p no:cacheprovider tests/test_cuda.py 2>&1 | tail -15

echo "== 2. svcode train on the GPU under cProfile"
timeout 120 bash -c '
svcode() { "$0" -m svcode_core.cli "$@"; }
svcode dataset --preset cm2-mini --frames 16 --out /tmp/probe-data --seed 99 --view-margin 16 \
  --departures training/cm2-mini-v2/departures.json --no-progress > /dev/null &&
"$0" -m cProfile -o /tmp/train.prof -m svcode_core.cli train --preset cm2-mini \
  --data /tmp/probe-data --out /tmp/probe --device ${DEVICE:-cuda} --view-margin 16 --batch-size 32 \
  --same-origin 8 --init src/svcode_core/weights/cm2-mini.safetensors --epochs 2 \
  --patches-per-epoch 320 --val-patches 32 --loader-workers 4 --no-progress 2>&1 | tail -2
cat /tmp/probe/log.csv | cut -d, -f1,12-14' "$PYTHON"
"$PYTHON" -c "
import pstats
stats = pstats.Stats('/tmp/train.prof')
stats.sort_stats('tottime').print_stats(25)
stats.sort_stats('cumulative').print_stats(30)" > "$out/train_profile.txt" 2>&1
grep -A 28 "tottime" "$out/train_profile.txt" | head -32 | cut -c1-150

echo "== 3. the network per part on AMX, one thread"
cp bench/results/network_parts.md /tmp/network_parts.before.md
OMP_NUM_THREADS=1 timeout 150 "$PYTHON" bench/network_parts.py 2>&1 | tail -3
cp bench/results/network_parts.md "$out/network_parts_amx.md"
cp bench/results/network_parts.json "$out/network_parts_amx.json"
cat "$out/network_parts_amx.md" | tail -6

echo "== 4. start-up and the 6-frame stack, two cores"
lscpu | grep -E "^Model name"
export OMP_NUM_THREADS=2
pin=(taskset -c 0,1)
"${pin[@]}" true 2>/dev/null || pin=()
echo "svcode --help: $(cpu "${pin[@]}" "$PYTHON" -m svcode_core.cli --help)"
echo "svcode reconstruct --help: $(cpu "${pin[@]}" "$PYTHON" -m svcode_core.cli reconstruct --help)"
svcode simulate --preset cm2-mini --object neurons --frames 6 --seed 3 --out /tmp/stack6 \
  > /dev/null 2>&1
for round in 1 2; do
  echo "round $round, LSV-ADMM fast point: $(cpu "${pin[@]}" "$PYTHON" -m svcode_core.cli \
    reconstruct /tmp/stack6/measurement.tif --system /tmp/stack6/system.json --out /tmp/a$round.tif \
    --method admm --rank 3 --iterations 10 --no-progress)"
  echo "round $round, SV-CoDe defaults: $(cpu "${pin[@]}" "$PYTHON" -m svcode_core.cli \
    reconstruct /tmp/stack6/measurement.tif --system /tmp/stack6/system.json --out /tmp/s$round.tif \
    --no-progress)"
  echo "round $round, SV-CoDe bf16: $(cpu "${pin[@]}" "$PYTHON" -m svcode_core.cli \
    reconstruct /tmp/stack6/measurement.tif --system /tmp/stack6/system.json --out /tmp/b$round.tif \
    --precision bf16 --no-progress)"
done
