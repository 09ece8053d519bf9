"""The experiment layer: set-ups, settings, run folders, training, evaluation, policy targets and sweeps."""
