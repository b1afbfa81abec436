"""python -m diffdlo.perception: train a perception network (diffdlo/perception/network.py)."""
import sys

from .network import main

sys.exit(main())
