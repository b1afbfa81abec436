"""The simulator's fused moves: the C++ CPU kernel (kernel.py, csrc/cable.cpp) and the Triton kernel on CUDA (triton_kernel.py)."""
