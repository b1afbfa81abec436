"""Using a trained run: load_policy, python -m agents.tools.evaluate, learning-curve plots."""
