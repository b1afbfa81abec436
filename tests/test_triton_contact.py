"""On the Triton engine (no contact in its kernel yet) a move with pegs or a pin runs the eager path, and the
Simulator says so in ``why_not["contact"]``. Marked ``triton`` like tests/test_triton_kernel.py (the interpreter on
the CPU: TRITON_INTERPRET=1 python -m pytest -m triton)."""
import pytest
import torch

import diffdlo

triton = pytest.importorskip("triton")
from benchmarks.contact_checks import line  # noqa: E402
from benchmarks.gradients import triton_gradients  # noqa: E402
from diffdlo.backends import triton_kernel  # noqa: E402

pytestmark = pytest.mark.triton
DEVICE = "cuda" if torch.cuda.is_available() else "cpu"
if DEVICE == "cpu" and not triton_kernel.interpreting():
    pytestmark = [pytest.mark.triton,
                  pytest.mark.skip(reason="no CUDA device: run with TRITON_INTERPRET=1 to test in the interpreter")]


def test_pegs_and_pins_on_the_triton_engine_run_the_eager_path(params):
    p = triton_gradients.short_params(params)
    tri = diffdlo.Simulator(p, device=DEVICE, dtype=torch.float64, backend="triton")
    ref = diffdlo.Simulator(p, device=DEVICE, dtype=torch.float64, backend="torch")
    assert tri.engine == "triton" and tri.contact_engine == "torch"
    assert "eager" in tri.why_not["contact"] and "contact" not in ref.why_not
    pos = line(p).to(DEVICE)
    pegs = torch.tensor([[float(pos[0, 18, 0]), 0.016, 0.01]], dtype=torch.float64, device=DEVICE)   # over node 18
    node, delta = torch.tensor([19], device=DEVICE), torch.tensor([[0.0, 0.05]], dtype=torch.float64, device=DEVICE)
    pin = torch.tensor([17], device=DEVICE)
    torch.testing.assert_close(tri.move(pos, node, delta, pegs, pin), ref.move(pos, node, delta, pegs, pin),
                               rtol=0, atol=0)
    without = tri.move(pos, node, delta)                          # the Triton kernel itself, without contact
    assert float((without - ref.move(pos, node, delta, pegs, pin)).abs().max()) > 1e-3
