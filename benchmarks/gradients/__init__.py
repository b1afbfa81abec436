"""Gradient benchmarks: APG's gradients, the Triton adjoint."""
