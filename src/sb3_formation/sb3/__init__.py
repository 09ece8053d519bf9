"""The Stable-Baselines3 layer: the VecEnv with one slot per agent, scale-only normalisation, the thesis's policies,
recurrent PPO (without sb3-contrib) and the curriculum and metrics callbacks."""
