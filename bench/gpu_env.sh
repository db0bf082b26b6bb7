# Sourced by the scripts that run on a GPU machine without network (bench/gpu_check.sh,
# bench/device_followup.sh, training/cm2-mini-v5/gpu.sh), from the repository root: the
# code runs from src/ (no build step), and the pure-Python packages the machine may lack
# (tqdm, pytorch-msssim) come from bench/gpu-wheels/ (bash bench/gpu_wheels.sh fills it)
# into a temporary folder removed when the script exits. Sets PYTHON and PYTHONPATH.
PYTHON=${PYTHON:-$(command -v python || command -v python3)}
export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
# import name:distribution of what the scripts import beyond the machine's own packages
missing=()
for pair in tqdm:tqdm pytorch_msssim:pytorch-msssim; do
    "$PYTHON" -c "import ${pair%%:*}" 2>/dev/null || missing+=("${pair#*:}")
done
if ((${#missing[@]})); then
    site=$(mktemp -d "${TMPDIR:-/tmp}/gpu-check-site.XXXXXX")
    trap 'rm -rf "$site"' EXIT
    echo "installing ${missing[*]} from bench/gpu-wheels/ into $site"
    if ! "$PYTHON" -m pip install --quiet --no-index --no-deps --find-links bench/gpu-wheels \
            --target "$site" "${missing[@]}"; then
        echo "pip could not install them; unpacking the wheels instead"
        for name in "${missing[@]}"; do
            for wheel in bench/gpu-wheels/"${name//-/_}"-*.whl; do
                [ -f "$wheel" ] && "$PYTHON" -m zipfile -e "$wheel" "$site"
            done
        done
    fi
    export PYTHONPATH="$site:$PYTHONPATH"
fi
