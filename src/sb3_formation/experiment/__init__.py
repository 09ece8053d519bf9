"""The experiment layer: recipes and their typed sections, run folders, training, evaluation, policy targets and sweeps."""
