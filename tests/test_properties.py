"""Property tests over random scenarios and actions: physical bounds and honest observation bounds."""

from __future__ import annotations

import math
import os

import numpy as np
from hypothesis import given, reject, settings
from hypothesis import strategies as st

from sb3_formation import FormationConfig, FormationEnv
from sb3_formation.env.config import OVERLAP_TOLERANCE
from sb3_formation.env.scenes import SCENES

TASKS = ["ch4-individual", "ch4-team", "ch5-angle", "ch5-bearing"]


@settings(max_examples=30, deadline=None)
@given(
    task=st.sampled_from(TASKS),
    n_agents=st.integers(3, 8),
    stage=st.integers(1, 3),
    seed=st.integers(0, 2**31 - 1),
    hold=st.integers(1, 60),
)
def test_physics_and_observations_stay_in_bounds(task: str, n_agents: int, stage: int, seed: int, hold: int) -> None:
    """Random pushes held for ``hold`` steps drive agents into walls, obstacles and each other."""
    config = FormationConfig.task(task, n_agents=n_agents, stage=stage)
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


#: The fuzz test's examples: bounded in ``make test``; a soak sets SB3_FORMATION_FUZZ_EXAMPLES (docs/guarantees.md).
FUZZ_EXAMPLES = int(os.environ.get("SB3_FORMATION_FUZZ_EXAMPLES", "40"))


@st.composite
def configs(draw: st.DrawFn) -> FormationConfig:
    """A task configuration anywhere in the validated limits the fuzz test covers (draws the config refuses, e.g. 16
    agents of 0.3 m, are drawn again)."""
    world = draw(st.sampled_from([(15.0, 10.0), (12.0, 8.0), (24.0, 16.0)]))
    try:
        config = FormationConfig.task(
            draw(st.sampled_from(TASKS)),
            n_agents=draw(st.integers(3, 16)),
            agent_radius=draw(st.floats(0.1, 0.3)),
            agent_mass=draw(st.floats(0.2, 5.0)),
            v_max=draw(st.floats(0.02, 1.0)),
            dt=draw(st.floats(0.05, 0.5)),
            max_force=draw(st.none() | st.floats(0.01, 1e4)),
            world_width=world[0],
            world_height=world[1],
            stage=draw(st.integers(1, 3)),
        )
        SCENES["curriculum"].check_fits(config)
    except ValueError:
        reject()
    return config


@settings(max_examples=FUZZ_EXAMPLES, deadline=None)
@given(
    config=configs(),
    seed=st.integers(0, 2**32 - 1),
    pattern=st.sampled_from(["corners", "huge", "to_centroid", "flip", "uniform"]),
    hold=st.integers(1, 8),
)
def test_fuzzed_configs_and_extreme_actions_keep_every_promise(
    config: FormationConfig, seed: int, pattern: str, hold: int
) -> None:
    """Every step, speeds stay within v_max, agents inside the walls, overlaps within OVERLAP_TOLERANCE of
    the radius (agents, obstacles, walls), observations finite and in the space, rewards finite and within the clip."""
    env = FormationEnv(config.replace(max_steps=120))
    observations, _ = env.reset(seed=seed)
    space, rng = env.observation_space("agent_0"), np.random.default_rng(seed)
    radius, size = config.agent_radius, np.array([config.world_width, config.world_height])
    tolerance = OVERLAP_TOLERANCE * radius
    actions = np.zeros((config.n_agents, 2))
    for step in range(120):
        positions = env.world.positions
        if step % hold == 0:
            actions = {
                "corners": rng.choice([-1.0, 1.0], size=actions.shape),
                "huge": rng.choice([-1e6, 1e6], size=actions.shape),  # clipped to [-1, 1]
                "to_centroid": positions.mean(axis=0) - positions,
                "flip": (positions.mean(axis=0) - positions) * (-1) ** (step // hold),
                "uniform": rng.uniform(-1, 1, size=actions.shape),
            }[pattern]
        observations, rewards, _, _, _ = env.step(dict(zip(env.agents, actions)))
        positions, velocities = env.world.positions, env.world.velocities
        assert np.all(np.hypot(velocities[:, 0], velocities[:, 1]) <= config.v_max * (1 + 1e-9))
        assert np.all(positions >= radius - tolerance) and np.all(positions <= size - radius + tolerance)
        gaps = np.hypot(*(positions[:, None] - positions[None]).transpose(2, 0, 1)) + np.eye(config.n_agents) * 9
        assert gaps.min() >= 2 * radius - tolerance
        if len(env.obstacles):
            to_obstacles = np.hypot(*(positions[:, None] - env.obstacles[None, :, :2]).transpose(2, 0, 1))
            assert np.all(to_obstacles >= env.obstacles[:, 2] + radius - tolerance)
        for agent, observation in observations.items():
            assert np.all(np.isfinite(observation)) and space.contains(observation)
            assert math.isfinite(rewards[agent]) and abs(rewards[agent]) <= config.reward_clip
        if not env.agents:
            break
