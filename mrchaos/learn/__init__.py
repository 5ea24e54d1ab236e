"""Learning: configs, policies, the curriculum, PPO, behaviour cloning, evaluation and checkpoints."""
