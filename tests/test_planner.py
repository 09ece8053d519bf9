"""The privileged planner: its plan and commands against hand-computed cases, the map it reads, and its episodes."""

from __future__ import annotations

import numpy as np
import pytest

from sb3_formation import FormationConfig, FormationEnv
from sb3_formation.controllers import CONTROLLERS
from sb3_formation.controllers.base import PrivilegedPolicy
from sb3_formation.controllers.planner import PlannerGains, PrivilegedPlanner
from sb3_formation.env.geometry import reference_polygon
from sb3_formation.env.scenarios import Scenario, start_formation
from sb3_formation.env.shapes import shape_gaps
from sb3_formation.experiment.evaluation import evaluate

CONFIG = FormationConfig.task("ch5-bearing", stage=3)  # n = 6, R_a 0.2 m, r_0 = 1.08 m, v_max 0.05 m/s


def passage_state(opening: float) -> tuple[FormationEnv, np.ndarray]:
    """A team at (3, 5), goal (12, 5), a wall across x = 7.5 with an opening of ``opening`` m centred on y = 5."""
    half = opening / 2 + 0.1
    walls = [[7.5, 0.0, 7.5, 5.0 - half, 0.2], [7.5, 5.0 + half, 7.5, 10.0, 0.2]]
    scenario = Scenario(start_formation(CONFIG, np.array([3.0, 5.0])), [12.0, 5.0], walls=walls)
    env = FormationEnv(CONFIG)
    observations, _ = env.reset(options={"scenario": scenario})
    return env, np.stack([observations[agent] for agent in env.agents])


def test_the_plan_shrinks_the_formation_to_the_opening() -> None:
    """Opening 1.6 m (wall faces at y = 4.2 and 5.8): at the opening the path runs through its middle (gap 0.8 m at
    the cell centre nearest y = 5, to within half a cell), so r = 0.8 - margin 0.08 - R_a 0.2 = 0.52 m; in the open,
    before the wall's reach, r is the starting 1.08 m; the path ends at the goal."""
    env, _ = passage_state(1.6)
    plan = PrivilegedPlanner(CONFIG).plan(env.team_state())
    at_wall = np.argmin(np.abs(plan.path[:, 0] - 7.5))
    assert abs(plan.path[at_wall, 1] - 5.0) <= 0.05 + 1e-9
    assert plan.radius[at_wall] == pytest.approx(0.8 - 0.08 - 0.2, abs=0.05 + 1e-9)
    assert plan.radius[0] == pytest.approx(CONFIG.start_circumradius)
    np.testing.assert_array_equal(plan.path[-1], [12.0, 5.0])
    assert np.all(np.diff(plan.arc) > 0)


def test_commands_by_hand() -> None:
    """Agents exactly at their places around a centroid on a straight path: every command is the centroid's velocity,
    speed 0.9 v_max = 0.045 m/s towards the carrot; one agent 0.1 m off its place adds k_position 0.1 = 0.05 m/s back."""
    env, _ = passage_state(2.4)
    planner = PrivilegedPlanner(CONFIG)
    plan = planner.plan(env.team_state())
    positions = np.array(env.team_state().positions)
    commands = planner.commands(plan, positions)
    direction = plan.path[np.searchsorted(plan.arc, plan.arc[plan.index] + 0.5)] - positions.mean(axis=0)
    expected = 0.045 * direction / np.linalg.norm(direction)
    places = positions.mean(axis=0) + reference_polygon(6, plan.radius[plan.index])
    np.testing.assert_allclose(commands, expected + 0.5 * (places - positions), atol=1e-12)
    np.testing.assert_allclose(places, positions, atol=1e-9)  # at the start the team is at its places


def test_it_reads_the_map_only_through_start_episodes() -> None:
    """Registered as ``controller:privileged-planner``, labelled privileged; without a plan a team stays still."""
    planner = CONTROLLERS["privileged-planner"](CONFIG)
    assert isinstance(planner, PrivilegedPolicy) and planner.privileged
    env, observations = passage_state(2.4)
    actions, _ = planner.predict(observations)
    np.testing.assert_array_equal(actions, 0.0)
    planner.start_episodes([0], [env.team_state()])
    actions, _ = planner.predict(observations)
    assert np.all(np.linalg.norm(actions, axis=1) > 0)
    with pytest.raises(ValueError, match="unknown gains"):
        PrivilegedPlanner(CONFIG, speed=0.5, turbo=1.0)
    with pytest.raises(ValueError, match=r"PlannerGains.margin=-1"):
        PlannerGains(margin=-1)


@pytest.mark.parametrize("scenes", ["passage", "corridor", "trap", "clutter", "mixed"])
def test_it_solves_every_family(scenes: str) -> None:
    """Four held-out episodes of each family (seed 500): all reach the goal, hardly touching anything."""
    planner = PrivilegedPlanner(CONFIG.replace(scenes=scenes))
    result = evaluate(planner, episodes=4, stage=3, seed=500, n_envs=4, record=0)
    assert result.summary["successes"] == 4
    assert result.summary["all_episodes"]["collisions_obstacle"]["mean"] <= 5


def test_it_plans_and_flies_through_a_small_maze() -> None:
    """Two walls from alternate sides force an S: the plan runs over the first wall's end and under the second's,
    every point of it clear of the walls by the smallest footprint plus the margin, and the team reaches the goal."""
    config = CONFIG.replace(max_steps=3000)
    walls = [[5.0, 0.0, 5.0, 7.0, 0.2], [10.0, 3.0, 10.0, 10.0, 0.2]]
    scenario = Scenario(start_formation(config, np.array([2.0, 3.0])), [13.0, 7.0], walls=walls)
    env = FormationEnv(config)
    observations, _ = env.reset(options={"scenario": scenario})
    planner = PrivilegedPlanner(config)
    plan = planner.plan(env.team_state())
    at_first, at_second = np.argmin(np.abs(plan.path[:, 0] - 5.0)), np.argmin(np.abs(plan.path[:, 0] - 10.0))
    assert plan.path[at_first, 1] > 7.1 and plan.path[at_second, 1] < 2.9
    gaps = shape_gaps(plan.path[1:-1], np.zeros((0, 3)), np.array(walls), config.world_width, config.world_height)
    assert gaps.min() >= 0.6 + 0.08 - 1e-9
    planner.start_episodes([0], [env.team_state()])
    for _ in range(config.max_steps):
        actions, _ = planner.predict(np.stack([observations[agent] for agent in env.possible_agents]))
        observations, _, terminated, truncated, _ = env.step(dict(zip(env.possible_agents, actions)))
        if any(terminated.values()) or any(truncated.values()):
            break
    assert env.team_state().goal_distance <= config.eta_g
