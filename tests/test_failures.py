"""Agents that fail: the ring of the flying agents by hand, the engine's re-formed team, and a team that loses an agent
at step 0 flying as a team of 5 beside a still circle."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sb3_formation.controllers.classical import ClassicalController
from sb3_formation.controllers.shrinking import ShrinkingController
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.disturbances import Disturbances, Failures, load_disturbances
from sb3_formation.env.engine import FormationEngine
from sb3_formation.env.geometry import flying_ring, flying_rows
from sb3_formation.env.observations import observation_layout
from sb3_formation.env.scenarios import Scenario, start_formation
from sb3_formation.env.sensors import AGENT_CHANNEL, OBSTACLE_CHANNEL

CONFIG = FormationConfig()  # n = 6 (Table 5.1)
FAILS_AT_START = CONFIG.replace(disturbances=Disturbances(failures=Failures(probability=1.0, steps=(0, 0))))


def test_a_failed_agent_leaves_the_ring_of_5() -> None:
    """Agent 2 of 0..5 fails: the ring 0-1-3-4-5 closes without it; places 0, 1, 2, 3, 4 for agents 0, 1, 3, 4, 5."""
    flying = np.array([True, True, False, True, True, True])
    ring = flying_ring(flying)
    assert ring.size == 5
    expected = {0: [5, 1], 1: [0, 3], 3: [1, 4], 4: [3, 5], 5: [4, 0]}
    for agent, neighbours in expected.items():
        assert ring.neighbours[agent].tolist() == neighbours
    assert ring.places[flying].tolist() == [0, 1, 2, 3, 4]
    places, rows = flying_rows(np.concatenate([np.ones(6, bool), flying]), 6)  # a second team of rows 6..11
    assert places[6:][flying].tolist() == [[0, 5], [1, 5], [2, 5], [3, 5], [4, 5]] and places[:6, 1].tolist() == [6] * 6
    assert rows[7].tolist() == [6, 9] and rows[9].tolist() == [7, 10]
    with pytest.raises(ValueError, match="at least 3 flying agents, 2 of 6"):
        flying_ring(np.array([True, False, False, True, False, False]))


def test_the_engine_re_forms_the_team_without_the_failed_agent() -> None:
    """After agent 2 fails: the ring of 5 in the constants, the pentagon's reference bearings (edge from place k to
    k + 1 at 180/5 + 72 k deg) and beta_ref = 108 deg, the failed agent on the obstacle channel, its motors stopped."""
    engine = FormationEngine([CONFIG])
    positions = start_formation(CONFIG, np.array([5.0, 5.0]))
    engine.reset(0, scenario=Scenario(positions, np.array([13.0, 5.0])))
    engine.fail(0, 2)
    constants = engine.constants
    assert constants.neighbours[3].tolist() == [1, 4] and constants.neighbours[1].tolist() == [0, 3]
    assert constants.beta_ref[0] == pytest.approx(108.0)
    for agent, place in ((0, 0), (1, 1), (3, 2), (4, 3), (5, 4)):
        to_next = math.radians(36.0 + 72.0 * place)
        to_previous = math.radians(36.0 + 72.0 * (place - 1) + 180.0)
        expected = [[math.cos(to_previous), math.sin(to_previous)], [math.cos(to_next), math.sin(to_next)]]
        np.testing.assert_allclose(constants.reference_bearings[agent], expected, atol=1e-12)
    layout = engine.lidars[0].layout
    assert layout.channels[-6:].tolist() == [AGENT_CHANNEL] * 2 + [OBSTACLE_CHANNEL] + [AGENT_CHANNEL] * 3
    assert layout.visible[1, -4] and layout.visible[3, -4]  # the failed agent: seen by its former neighbours too
    assert not layout.visible[1, -3] and layout.visible[0, -3]  # agent 3, agent 1's new neighbour: not on its channel
    with pytest.raises(ValueError, match="agent 2 of team 0 does not fly"):
        engine.fail(0, 2)
    still = engine.latest.positions[2].copy()
    step = engine.step(np.tile([1.0, 0.0], (6, 1)))
    np.testing.assert_array_equal(step.positions[2], still)  # its motors stopped: it stands
    assert step.positions[0, 0] > positions[0, 0]
    state = engine.team_state(0)
    assert state.flying is not None and state.flying.tolist() == [True, True, False, True, True, True]
    np.testing.assert_allclose(state.centroid, step.positions[[0, 1, 3, 4, 5]].mean(axis=0), atol=1e-12)
    layout_of = observation_layout(engine.observation_fields)
    offsets = step.observations[3, layout_of["neighbour_offsets"]].reshape(2, 2)
    np.testing.assert_allclose(offsets, step.positions[[1, 4]] - step.positions[3], atol=1e-5)  # float32 observations
    engine.reset(0, scenario=Scenario(positions, np.array([13.0, 5.0])))  # the next episode: the ring of 6 again
    assert constants.neighbours[3].tolist() == [2, 4] and constants.beta_ref[0] == pytest.approx(120.0)
    assert engine.lidars[0].layout.channels[-4] == AGENT_CHANNEL and engine.team_state(0).flying is None


@pytest.mark.parametrize("controller", [ClassicalController, ShrinkingController])
def test_a_team_that_loses_an_agent_at_step_0_flies_as_a_team_of_5(controller: type) -> None:
    """A team of 6 whose agent fails at step 0 against a team of 5 at the flying agents' places with a still circle
    of radius R_a where the failed agent stands: the same observations, rewards and path to the goal."""
    positions, goal = start_formation(CONFIG, np.array([3.0, 5.0])), np.array([5.0, 5.4])
    failing = FormationEngine([FAILS_AT_START])
    first = failing.reset(0, seed=3, scenario=Scenario(positions, goal))
    failed = int(failing.failures.agents[0]) if failing.failures is not None else -1
    flying = np.arange(6) != failed
    assert failed >= 0 and failing.team_state(0).flying.tolist() == flying.tolist()
    five = CONFIG.replace(n_agents=5)
    obstacle = np.array([[*positions[failed], CONFIG.agent_radius]])
    team = FormationEngine([five])
    # the flying agents in their ring order: agent k of the team of 5 is the flying agent of place k
    second = team.reset(0, scenario=Scenario(positions[flying], goal, obstacle))
    np.testing.assert_array_equal(first[flying], second)
    policy, alone = controller(FAILS_AT_START), controller(five)
    state = alone_state = None
    for _ in range(300):
        actions, state = policy.predict(first, state, flying=np.repeat(flying[None], 1, 0).reshape(-1))
        alone_actions, alone_state = alone.predict(second, alone_state)
        np.testing.assert_allclose(actions[flying], alone_actions, atol=1e-9)
        step, other = failing.step(actions), team.step(alone_actions)
        np.testing.assert_allclose(step.positions[flying], other.positions, atol=1e-9)
        np.testing.assert_allclose(step.rewards[flying], other.rewards, atol=1e-9)
        np.testing.assert_allclose(step.observations[flying], other.observations, atol=1e-5)
        assert step.terminated[0] == other.terminated[0]
        first, second = step.observations, other.observations
        if other.terminated[0]:
            break
    assert other.terminated[0], "the team of 5 reaches the goal"  # so the comparison covered a whole episode
    assert step.contacts[flying].sum() == 0
    summary = failing.episode_summary(0)
    assert summary["failed_agents"] == 1 and summary["success"]
    np.testing.assert_allclose(summary["angle_error_deg"], team.episode_summary(0)["angle_error_deg"], atol=1e-9)


def test_failures_are_drawn_from_their_own_stream_and_validated() -> None:
    """Half the episodes lose an agent (probability 0.5), at a step within the window, the same for the same seed."""
    config = CONFIG.replace(disturbances=Disturbances(failures=Failures(probability=0.5, steps=(5, 40))))
    engine = FormationEngine([config])
    draws = []
    for seed in range(200):
        engine.reset(0, seed=seed)
        assert engine.failures is not None
        draws.append((int(engine.failures.agents[0]), int(engine.failures.steps[0])))
    failing = [draw for draw in draws if draw[0] >= 0]
    assert 70 <= len(failing) <= 130  # binomial(200, 0.5): 100 +- 4.2 sigma
    assert all(5 <= step <= 40 for _, step in failing) and {agent for agent, _ in failing} == set(range(6))
    engine.reset(0, seed=7)
    assert (int(engine.failures.agents[0]), int(engine.failures.steps[0])) == draws[7]
    assert engine.disturber is None  # failures alone disturb no signal
    assert Disturbances(failures=Failures(probability=0.5, steps=(5, 40))).scaled(0.0).is_ideal
    scaled = load_disturbances({"failures": {"probability": 0.5, "steps": [5, 40]}}).scaled(2.0)
    assert scaled.failures == Failures(probability=1.0, steps=(5, 40))  # a probability capped at 1, the window kept
    with pytest.raises(ValueError, match=r"failures.steps=.*whole steps"):
        Failures(probability=0.5, steps=(0.5, 3))
    with pytest.raises(ValueError, match=r"failures.probability=1.5 is invalid"):
        Failures(probability=1.5)


def test_evaluation_tells_every_kind_of_policy_which_agents_fly() -> None:
    """Episodes of a task whose agents fail at step 0 through the episode loop: each reports one failed agent, and a
    shipped residual policy (its controller at the places of the ring of 5) and the filter play them."""
    from sb3_formation.experiment.evaluation import evaluate
    from sb3_formation.experiment.targets import load_policy

    overrides = {"disturbances": FAILS_AT_START.disturbances}
    for target in ("controller:shrinking", "safe:pretrained:scenes-ch5-bearing"):
        result = evaluate(load_policy(target), 4, n_envs=4, env_overrides=overrides, record=0)
        assert [row["failed_agents"] for row in result.episodes] == [1, 1, 1, 1]
        assert result.summary["all_episodes"]["failed_agents"]["mean"] == 1.0
