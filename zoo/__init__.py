"""zoo: the RL-Zoo front end of vafn (training, tuning, plots, reproduction); wraps rl_zoo3, never forks it."""
