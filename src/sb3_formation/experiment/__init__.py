"""The experiment layer: recipes, settings, run folders, training, evaluation, policy targets and sweeps."""
