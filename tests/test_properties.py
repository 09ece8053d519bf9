"""Property tests over random scenarios and actions: physical bounds and honest observation bounds."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from sb3_formation import FormationConfig, FormationEnv

PRESETS = ["ch4-individual", "ch4-team", "ch5-angle", "ch5-bearing"]


@settings(max_examples=30, deadline=None)
@given(
    preset=st.sampled_from(PRESETS),
    n_agents=st.integers(3, 8),
    stage=st.integers(1, 3),
    seed=st.integers(0, 2**31 - 1),
    hold=st.integers(1, 60),
)
def test_physics_and_observations_stay_in_bounds(preset: str, n_agents: int, stage: int, seed: int, hold: int) -> None:
    """Random pushes held for ``hold`` steps drive agents into walls, obstacles and each other."""
    config = FormationConfig.preset(preset, n_agents=n_agents, stage=stage)
    env = FormationEnv(config)
    observations, _ = env.reset(seed=seed)
    space = env.observation_space("agent_0")
    rng = np.random.default_rng(seed)
    radius, width, height = config.agent_radius, config.world_width, config.world_height
    actions = {}
    for step in range(240):
        if step % hold == 0:
            actions = {agent: rng.uniform(-1.5, 1.5, 2) for agent in env.agents}  # beyond [-1, 1]: clipped
        observations, _, _, _, _ = env.step(actions)
        positions, velocities = env.world.positions, env.world.velocities
        assert np.all(positions >= radius - 0.01) and np.all(positions <= np.array([width, height]) - radius + 0.01)
        for x, y, obstacle_radius in env.obstacles:
            centre_distances = np.hypot(positions[:, 0] - x, positions[:, 1] - y)
            assert np.all(centre_distances >= obstacle_radius + radius - 0.01)
        assert np.all(np.hypot(velocities[:, 0], velocities[:, 1]) <= config.v_max + 1e-6)
        for observation in observations.values():
            assert np.all(np.isfinite(observation))
            assert space.contains(observation), np.flatnonzero((observation < space.low) | (observation > space.high))
        if not env.agents:
            break
