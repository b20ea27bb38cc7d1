#!/usr/bin/env bash
# Every GPU check and figure the docs quote, in one go on a GPU machine that already has torch,
# numba and numba-cuda (the rest can come as wheels in .whl/, installed to /tmp/site; the paper's
# reference layer needs einops and jaxtyping: `pip download --no-deps -d .whl einops jaxtyping
# wadler-lindig`):
#
#     bash examples/gpu_all.sh [OUTDIR]      # OUTDIR defaults to $OUT, else examples/gpu
#
# In order of importance, so a run cut short keeps the first: what `layoutwarp doctor` sees, the
# CUDA tests and the figures of examples/gpu_check.py (the first call from an empty cache
# included), the training step of examples/gpu_training_step.py, and the bench on the device.
set -u
dest=${1:-${OUT:-examples/gpu}}
mkdir -p "$dest"
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
if compgen -G ".whl/*.whl" > /dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
        && export PYTHONPATH="$PYTHONPATH:/tmp/site"
fi
python3 -m layoutwarp doctor 2>&1 | tee "$dest/doctor.txt"
python3 examples/gpu_check.py --out "$dest/gpu_check.json" 2>&1 | tee "$dest/gpu_check.txt"
python3 examples/gpu_training_step.py 2>&1 | tee "$dest/gpu_training_step.txt"
timeout 110 python3 -m layoutwarp bench --threads 16 --device cuda --layouts "curv,curv ±" --no-scaling \
    --no-memory --text "$dest/bench_cuda.txt" --json "$dest/bench_cuda.json" 2>&1 | tail -40
