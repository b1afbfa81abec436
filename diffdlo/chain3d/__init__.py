"""The 3-D chain beside the planar model: a cable in 3-D under gravity (``chain``), DEFORM's motion-capture recordings
of five real cables (``deform``), the chain fitted to them (``fit``) and a learned residual on top (``residual``)."""
