#!/usr/bin/env bash
# Every GPU check and figure the docs quote, in one go on a GPU machine that already has torch,
# numba and numba-cuda (the rest can come as wheels in .whl/, installed to /tmp/site: kornia,
# kornia_rs and shapely where missing; the paper's reference layer, for the step's comparison,
# in shared/refcode inside or beside the checkout, needs einops and jaxtyping):
#
#     bash examples/gpu_all.sh [OUTDIR]      # OUTDIR defaults to $OUT, else examples/gpu
#
# In order of importance, so a run cut short keeps the first: what `layoutwarp doctor` sees, the
# figures of examples/gpu_check.py (the first call from an empty cache included) and then the
# CUDA tests (its JSON is written after each part), and the training step of
# examples/gpu_training_step.py.
set -u
dest=${1:-${OUT:-examples/gpu}}
mkdir -p "$dest"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
if compgen -G ".whl/*.whl" > /dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        && export PYTHONPATH="$PYTHONPATH:/tmp/site"
fi
nvidia-smi --query-gpu=name,driver_version,clocks.sm,clocks.mem --format=csv,noheader
python3 -c "import layoutwarp as lw, torch; lw.simulate(torch.rand(1, 8, 8), lw.CurvLayout((0.1, 0.1)), (2, 2))" \
    || { echo "gpu_all: layoutwarp does not import or run here"; exit 1; }
python3 -m layoutwarp doctor 2>&1 | tee "$dest/doctor.txt"
timeout "${GPU_CHECK_S:-420}" python3 examples/gpu_check.py --out "$dest/gpu_check.json" 2>&1 | tee "$dest/gpu_check.txt"
timeout "${TRAINING_STEP_S:-60}" python3 examples/gpu_training_step.py 2>&1 | tee "$dest/gpu_training_step.txt"
