"""Fitting the model to recordings: the recording format (recording.py), synthetic recordings (record.py) and the fit (calibrate.py)."""
