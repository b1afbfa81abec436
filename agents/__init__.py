"""Model-free learners on the diffdlo shape-control env: SAC (agents.sac), PPO (agents.ppo).

``agents.buffer.ReplayBuffer`` is the one storage for every learner; ``agents.common`` holds the shared env wrapper
(batched, own autoreset), network builders, logger, checkpoints and ``evaluate``; ``agents.plot`` draws learning
curves from the CSV logs.
"""
