"""Speed benchmarks: the simulator, the env, the Triton kernels."""
