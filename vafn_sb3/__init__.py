"""vafn_sb3: MAML-SAC, the MARL baselines and the online adaptive controller, as Stable-Baselines3 algorithms."""
