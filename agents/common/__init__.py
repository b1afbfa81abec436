"""The pieces every learner shares: config, command line, run, env, buffer, evaluation, logs, checkpoints."""
