"""A real cable: DEFORM's motion-capture recordings (deform.py) and the chain in 3-D under gravity (chain3d.py)."""
