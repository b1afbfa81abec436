"""Benchmarks and the comparison harness (python -m benchmarks.compare). Not part of the installed package."""
