"""Learners on the diffdlo shape-control env: SAC (agents.sac), PPO (agents.ppo), PlaNet (agents.planet).

Each learner file is its algorithm, top to bottom: config -> networks -> loop. What they share, by concern:
``config`` (the options every run shares, composed into each config; presets), ``cli`` (the command line),
``run`` (the envs, counters, logs, evaluation/checkpoint schedule, resume and results of one run), ``envs`` (the
training env with same-step autoreset), ``networks`` (MLPs, CNN encoders), ``evaluation``, ``logs``,
``checkpoints``, ``buffer`` (the one replay storage), ``hybrid`` (the node + drag action head, relative features).
PlaNet's world models are in ``dynamics`` (the ensemble) and ``rssm``; ``openloop`` checks their predictions;
``plot`` draws learning curves from the CSV logs.

A trained run is used through ``policy`` (``agents.load_policy(RUN_DIR)``: the learner's networks rebuilt from its
checkpoint, acting on one gymnasium observation or on batches) and ``evaluate`` (``python -m agents.tools.evaluate
RUN_DIR``: its success rate on the run's task or another target, final shapes and a GIF of the first episodes).
"""

__all__ = ["load_policy"]


def __getattr__(name: str):
    """``agents.load_policy`` imported on first use: ``import agents`` stays light (no learner imported)."""
    if name == "load_policy":
        from agents.tools.policy import load_policy
        return load_policy
    raise AttributeError(f"module 'agents' has no attribute {name!r}")
