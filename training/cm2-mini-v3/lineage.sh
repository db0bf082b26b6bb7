#!/usr/bin/env bash
# cm2-mini v3: one variant of the lens-context model through the bundled model's whole
# recipe, resumable over sessions: context-scratch.sh VARIANT (20 epochs from scratch), then
# finetune.sh context-ring-VARIANT (6 epochs) and context-ring4-VARIANT (8 epochs). When a
# stage ends its resume state is copied into its folder here (../cm2-mini-v2/snapshot.sh),
# where the next stage takes its initial weights from, and its best weights are scored
# by ../../bench/ring_gap.py (the outer ring against the centre on the same content, both
# regimes, about 2 minutes; a failure there does not stop the training) into ring-gap.md
# there; a finished stage is passed over.
# About 7.3 CPU-hours on one thread from scratch, as for the bundled model.
#   no-coordgate, no-pe   the ablations, at the bundled model's budget
#   reach2                the lens context reaching two pitches left and right
# Usage (from the repository root): bash training/cm2-mini-v3/lineage.sh VARIANT
set -euo pipefail
variant="${1:-}"
case "$variant" in
  no-coordgate|no-pe|reach2) ;;
  *) echo "lineage: no-coordgate, no-pe or reach2" >&2; exit 2;;
esac
here="$(cd "$(dirname "$0")" && pwd)"

finished() {  # copy a finished stage here and score its best weights, unless done before
  local stage="$1"
  bash "$here/../cm2-mini-v2/snapshot.sh" "runs/v3-$stage" "$here/$stage"
  [ "$here/$stage/ring-gap.md" -nt "$here/$stage/best.safetensors" ] ||
    python "$here/../../bench/ring_gap.py" --weights "$here/$stage/best.safetensors" \
      --no-admm --out "$here/$stage/ring-gap" ||
    echo "lineage: scoring $stage failed; training goes on" >&2
}

bash "$here/context-scratch.sh" "$variant"
finished "context-scratch-$variant"
for arm in context-ring context-ring4; do
  bash "$here/finetune.sh" "$arm-$variant"
  finished "$arm-$variant"
done
