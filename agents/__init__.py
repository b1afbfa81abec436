"""Learners on the diffdlo shape-control env: SAC (agents.sac), PPO (agents.ppo), PlaNet (agents.planet).

Each learner file is its algorithm, top to bottom: config -> networks -> loop. What they share, by concern:
``config`` (the options every run shares, composed into each config; presets), ``cli`` (the command line),
``run`` (the envs, counters, logs, evaluation/checkpoint schedule, resume and results of one run), ``envs`` (the
training env with same-step autoreset), ``networks`` (MLPs, CNN encoders), ``evaluation``, ``logs``,
``checkpoints``, ``buffer`` (the one replay storage), ``hybrid`` (the node + drag action head, relative features).
PlaNet's world models are in ``dynamics`` (the ensemble) and ``rssm``; ``openloop`` checks their predictions;
``plot`` draws learning curves from the CSV logs.
"""
