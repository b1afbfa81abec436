"""One-off studies: ablations, calibration, model mismatch, world models, SB3 checks."""
