"""The privileged crowd baseline (``controller:crowd``): the shrinking controller's velocity made collision-free by
navground's ORCA, given the moving obstacles' velocities."""

from __future__ import annotations

import navground.core as crowd_core
import numpy as np
import pytest

from sb3_formation.controllers import CONTROLLERS, CrowdController
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.state import TeamState
from sb3_formation.experiment.evaluation import evaluate_target

CONFIG = FormationConfig.task("ch5-bearing", stage=3, n_agents=3)  # v_max 0.05 m/s, dt 0.3 s, R_a 0.2 m, m 1 kg
PUSH = CONFIG.force_max * CONFIG.dt / CONFIG.agent_mass  # m/s of a unit action over a step (v_max: F_max = m v_max / dt)


def team_state(mover_velocity: tuple[float, float]) -> TeamState:
    """Three agents far apart, agent 0 at (5, 5) flying +x at v_max; a mover of radius 0.3 m 0.7 m ahead of it."""
    positions = np.array([[5.0, 5.0], [5.0, 8.0], [10.0, 8.0]])
    velocities = np.array([[CONFIG.v_max, 0.0], [0.0, 0.0], [0.0, 0.0]])
    zeros = np.zeros(3)
    return TeamState(
        step=1,
        positions=positions,
        velocities=velocities,
        goal=np.array([12.0, 5.0]),
        obstacles=np.array([[5.7, 5.0, 0.3]]),
        neighbours=np.array([[2, 1], [0, 2], [1, 0]]),
        contacts_agent=zeros,
        contacts_obstacle=zeros,
        angle_errors_deg=zeros,
        bearing_errors=zeros,
        neighbour_distance_errors=zeros,
        centroid=positions.mean(axis=0),
        goal_distance=7.0,
        obstacle_velocities=np.array([mover_velocity]),
        moving=1,
    )


def test_orca_holds_an_agent_back_from_a_mover_coming_head_on() -> None:
    """Agent 0 keeps flying +x (action 0 holds v_max) at a mover coming head-on at v_max: its action commands exactly
    the velocity navground's ORCA gives for the same neighbour (computed here on its own), which no longer flies at
    the mover at full speed; the agents with nothing near keep their actions; a mover going away changes nothing."""
    controller = CrowdController(CONFIG)
    state = team_state((-CONFIG.v_max, 0.0))
    actions = np.zeros((3, 2))
    safe = controller.avoid(state, actions)
    behavior = crowd_core.behaviors.ORCABehavior(
        kinematics=crowd_core.kinematics.OmnidirectionalKinematics(max_speed=CONFIG.v_max), radius=CONFIG.agent_radius
    )
    behavior.time_horizon, behavior.safety_margin = 5.0, 0.02
    behavior.position, behavior.velocity = (5.0, 5.0), (CONFIG.v_max, 0.0)
    behavior.target = crowd_core.Target.Velocity(np.array([CONFIG.v_max, 0.0]))
    behavior.environment_state.neighbors = [crowd_core.Neighbor(np.array([5.7, 5.0]), 0.3, np.array([-CONFIG.v_max, 0.0]))]
    corners = [(0.0, 0.0), (15.0, 0.0), (15.0, 10.0), (0.0, 10.0)]
    behavior.environment_state.line_obstacles = [
        crowd_core.LineSegment(a, b) for a, b in zip(corners, corners[1:] + corners[:1])
    ]
    expected = np.asarray(behavior.compute_cmd(CONFIG.dt).velocity, dtype=float)
    commanded = state.velocities[0] + safe[0] * PUSH
    assert commanded == pytest.approx(expected, abs=1e-6)
    assert commanded[0] < 0.8 * CONFIG.v_max  # it no longer flies at the mover at full speed
    assert safe[1:] == pytest.approx(np.zeros((2, 2)), abs=1e-6)
    away = controller.avoid(team_state((CONFIG.v_max, 0.0)), actions)
    assert away == pytest.approx(np.zeros((3, 2)), abs=1e-6)


def test_the_crowd_baseline_is_a_privileged_controller_of_holonomic_agents() -> None:
    """It is ``controller:crowd``, labelled privileged, refuses unicycles in one line, and plays evaluation episodes
    of a crowd, reading every team's state at every step (its summary counts the movers that ran into agents)."""
    assert CONTROLLERS["crowd"] is CrowdController and CrowdController.privileged
    with pytest.raises(ValueError, match="controller:crowd steers holonomic agents; this task's are unicycle"):
        CrowdController(CONFIG.replace(dynamics="unicycle"))
    result = evaluate_target("controller:crowd", changes={"episodes": 2, "n_envs": 2}, env_overrides={"scenes": "crowd"})
    assert result.summary["episodes"] == 2 and "collisions_rammed" in result.summary["all_episodes"]
