"""The renderer inverted: node positions read from the env's pictures (obs "perceived").

network.py holds the network, the reader (``Perception``) and its training; ``python -m diffdlo.perception --out
DIR`` trains one. boards.py draws ropes among a route's pegs (the routing task's pictures).
"""
from .network import (CHECKPOINT, DEFAULT_VIEW_SIZE, FORMAT, Perception, PerceptionError, PerceptionNet, TrainConfig,
                      augmented_batch, board_coverage, board_pool, draw, evaluate, held_out, ink, main, node_error,
                      plot, refine, render_uint8, sample_shapes, train, unpeg)

__all__ = ["CHECKPOINT", "DEFAULT_VIEW_SIZE", "FORMAT", "Perception", "PerceptionError", "PerceptionNet",
           "TrainConfig", "augmented_batch", "board_coverage", "board_pool", "draw", "evaluate", "held_out", "ink", "main",
           "node_error", "plot", "refine", "render_uint8", "sample_shapes", "train", "unpeg"]
