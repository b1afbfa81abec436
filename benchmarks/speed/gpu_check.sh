#!/usr/bin/env bash
# The prepared GPU check of the Triton backend, forward and adjoint (issues 23 and 35), < 9 min on an H100/H200:
#   bash benchmarks/speed/gpu_check.sh        (outputs under $OUT if set, else runs/gpu_check)
set -uo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-python}
[ -x .venv/bin/python ] && PY=.venv/bin/python
OUTDIR=${OUT:-runs/gpu_check}
mkdir -p "$OUTDIR"
nvidia-smi > "$OUTDIR/nvidia-smi.txt" 2>&1 || true
$PY -c "import triton" 2>/dev/null || $PY -m pip install -q -e ".[gpu]" > "$OUTDIR/pip.txt" 2>&1 || $PY -m pip install -q "triton>=3.0" >> "$OUTDIR/pip.txt" 2>&1
$PY -c "import torch, triton; print(torch.__version__, torch.cuda.is_available(), triton.__version__)" | tee "$OUTDIR/versions.txt"
# the kernels' tests, compiled on CUDA (no interpreter): the move, the adjoint's gradients against eager autograd
TRITON_INTERPRET=0 timeout 150 $PY -m pytest -m triton -q -p no:cacheprovider tests/test_triton_kernel.py 2>&1 | tee "$OUTDIR/pytest_triton.txt"
# the compiled adjoint's gradients against eager autograd, per input and dtype (the tests' problem)
TRITON_INTERPRET=0 timeout 60 $PY -m benchmarks.gradients.triton_gradients --device cuda 2>&1 | tee "$OUTDIR/triton_gradients.txt"
# forward, and forward+backward through the Triton adjoint at every B (bwd/fwd, peak GPU memory, gradient deviation)
timeout 240 $PY benchmarks/speed/sim_speed.py --device cuda --batches 1 64 1024 16384 65536 --repeats 3 \
    --eager-max 1024 --backward-max 65536 --cpu-max 16384 2>&1 | tee "$OUTDIR/sim_speed_cuda.txt"
timeout 90 $PY benchmarks/speed/env_speed.py --device cuda --batches 1 64 1024 65536 --steps 2 --min-time 1 \
    --eager-max 64 --cpu-max 1024 2>&1 | tee "$OUTDIR/env_speed_cuda.txt"
echo "outputs in $OUTDIR"
