"""The safety filter among moving obstacles: a declared bound on their speed enters the obstacle barrier (worst-case
approach), contacts are split into those the agents drove into and those where a faster obstacle ran into them."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_safety import adversarial_actions

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.families import MOVING_FAMILIES
from sb3_formation.env.formation_env import FormationEnv
from sb3_formation.env.movers import Mover
from sb3_formation.env.observations import observation_fields, observation_layout
from sb3_formation.env.scenarios import Scenario
from sb3_formation.env.scenes import scenes_named
from sb3_formation.safety import SafetyFilter, SafetyGains

CONFIG = FormationConfig.task("ch5-bearing", stage=3, n_agents=3)  # v_max = 0.05 m/s, dt = 0.3 s, R_a = 0.2 m
V_MAX, DT = CONFIG.v_max, CONFIG.dt
#: a team of 3 in a row along x, 1.3 m apart, agent 0 in the middle; a mover comes at agent 0 from below
TEAM = np.array([[7.5, 5.0], [6.2, 5.0], [8.8, 5.0]])


def head_on(speed: float) -> Scenario:
    """A mover of radius 0.3 m starting 1 m below agent 0's surface, heading straight up at ``speed`` (m/s)."""
    return Scenario(TEAM, np.array([7.5, 9.0]), movers=(Mover(0.3, [[7.5, 3.5], [7.5, 9.5]], speed, "path"),))


def play(scenario: Scenario, gains: SafetyGains | None, steps: int) -> tuple[np.ndarray, dict[str, int], int]:
    """Every agent proposes to stand still (action 0) for ``steps`` steps, behind the filter with ``gains`` (``None``:
    no filter): agent 0's positions, the contacts summed over the steps, and the steps reported infeasible."""
    env = FormationEnv(CONFIG)
    rows = np.stack(list(env.reset(seed=0, options={"scenario": scenario})[0].values()))
    safety = None if gains is None else SafetyFilter(CONFIG, gains)
    positions, totals, infeasible = [], {"collisions_obstacle": 0, "collisions_rammed": 0, "collisions_agent": 0}, 0
    for _ in range(steps):
        actions = np.zeros((CONFIG.n_agents, 2))
        if safety is not None:
            actions, report = safety.filter(rows, actions)
            infeasible += int(report.infeasible.any())
        rows, _, _, _, infos = env.step_array(actions)
        for key in totals:
            totals[key] += sum(info[key] for info in infos)
        positions.append(env.team_state().positions[0])
    return np.array(positions), totals, infeasible


def test_an_obstacle_approaching_head_on_at_the_bound_makes_the_agent_yield() -> None:
    """At v_max with the bound at v_max: unfiltered, the mover runs into the standing agent (a rammed contact, not one
    it drove into); behind the filter the agent backs away along +y and nothing touches, every step feasible."""
    _, unfiltered, _ = play(head_on(V_MAX), None, 120)
    assert unfiltered["collisions_obstacle"] > 0 and unfiltered["collisions_rammed"] == unfiltered["collisions_obstacle"]
    positions, filtered, infeasible = play(head_on(V_MAX), SafetyGains(obstacle_speed=V_MAX), 120)
    assert filtered == {"collisions_obstacle": 0, "collisions_rammed": 0, "collisions_agent": 0} and infeasible == 0
    assert positions[-1, 1] - 5.0 > 0.5 and abs(positions[-1, 0] - 7.5) < 0.05  # it yielded straight away from it


def test_an_obstacle_faster_than_the_bound_runs_into_the_agent() -> None:
    """At twice v_max against a bound of v_max the agent cannot back away fast enough: the contacts come, each counted
    as the mover running into the agent, on steps the filter reports infeasible."""
    _, totals, infeasible = play(head_on(2 * V_MAX), SafetyGains(obstacle_speed=V_MAX), 120)
    assert totals["collisions_obstacle"] > 0 and totals["collisions_rammed"] == totals["collisions_obstacle"]
    assert infeasible > 0


def test_the_scenes_declare_the_bound_of_their_movers() -> None:
    """The filter's default bound is the one the task's scenes declare: 0 where nothing moves, the fastest mover of a
    family (1.5 v_max in ``crowd``, v_max in ``crowd-blind``)."""
    assert SafetyFilter(CONFIG).obstacle_speed == 0.0
    assert SafetyFilter(CONFIG.replace(scenes="crowd")).obstacle_speed == pytest.approx(1.5 * V_MAX)
    assert SafetyFilter(CONFIG.replace(scenes="crowd-blind")).obstacle_speed == pytest.approx(V_MAX)
    assert scenes_named("mixed-moving").obstacle_speed(CONFIG) == pytest.approx(1.5 * V_MAX)
    assert SafetyFilter(CONFIG.replace(scenes="crowd"), SafetyGains(obstacle_speed=0.01)).obstacle_speed == 0.01
    with pytest.raises(ValueError, match=r"SafetyGains\.obstacle_speed=-1"):
        SafetyGains(obstacle_speed=-1)


def goal_seeking_actions(rows: np.ndarray, config: FormationConfig, rng: np.random.Generator) -> np.ndarray:
    """Every agent pushes towards the goal (its row's centroid-goal offset) plus noise: teams cross the movers' lines."""
    offsets = rows[:, observation_layout(observation_fields(config))["centroid_goal_offset"]]
    directions = offsets / np.maximum(np.linalg.norm(offsets, axis=1, keepdims=True), 1e-9)
    return np.clip(directions + rng.normal(0.0, 0.3, offsets.shape), -1.0, 1.0)


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    scenes=st.sampled_from(sorted(MOVING_FAMILIES)),
    n_agents=st.integers(3, 6),
    seed=st.integers(0, 10_000),
    kind=st.sampled_from(["goal", "nearest", "random"]),
)
def test_no_contacts_except_on_reported_infeasible_steps_among_movers_within_the_bound(
    scenes: str, n_agents: int, seed: int, kind: str
) -> None:
    """In random scenes of every family with moving obstacles (within the family's declared speed), agents heading
    for the goal, driving at whatever is nearest, or at random, behind the filter: no contact of any kind (the agents
    drove into it or a mover ran into them) on a step the filter reported feasible."""
    config = CONFIG.replace(scenes=scenes, n_agents=n_agents)
    env = FormationEnv(config)
    safety = SafetyFilter(config)
    rng = np.random.default_rng(seed)
    rows = np.stack(list(env.reset(seed=seed)[0].values()))
    for _ in range(400):
        proposed = goal_seeking_actions(rows, config, rng) if kind == "goal" else adversarial_actions(rows, config, rng, kind)
        safe, report = safety.filter(rows, proposed)
        rows, _, terminated, truncated, infos = env.step_array(safe)
        touched = sum(info["collisions_agent"] + info["collisions_obstacle"] for info in infos)
        if touched:
            assert report.infeasible.any(), f"a contact on a step the filter reported feasible ({scenes}, n={n_agents})"
        if terminated or truncated:
            break
