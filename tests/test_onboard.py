"""The on-board pipeline without ROS (:mod:`sb3_formation.ros.onboard`): over whole episodes it gives the simulator's
own rows and the policy's own actions and commands, and the agent node is a shell over it."""

from __future__ import annotations

import ast
import math
import re
from pathlib import Path

import numpy as np
import pytest

from sb3_formation.controllers import ShrinkingController
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.dynamics import dynamics_model
from sb3_formation.env.formation_env import FormationEnv
from sb3_formation.ros.onboard import AgentSettings, Onboard, TeamView
from sb3_formation.ros.scans import Scan, merged_scan
from sb3_formation.safety.policy import SafePolicy

STAGE_3 = FormationConfig.task("ch5-bearing", stage=3)
UNICYCLE_STAGE_3 = FormationConfig.task("ch5-bearing", stage=3, dynamics="unicycle")
PACKAGE = Path(__file__).resolve().parents[1] / "src" / "sb3_formation"


@pytest.mark.parametrize("config", [STAGE_3, UNICYCLE_STAGE_3], ids=["holonomic", "unicycle"])
def test_the_onboard_pipeline_flies_the_simulators_episode(config: FormationConfig) -> None:
    """Six :class:`Onboard` pipelines (the shrinking controller, which keeps a memory, behind the safety filter), each
    fed its agent's scan in its own body frame (every obstacle, seen through teammates: the simulator's obstacle
    channel), the team's poses and the goal, fly a whole stage-3 episode (500 steps): every step, each row is the
    simulator's row (the lidar within 1e-6 of the range, the rest within 1e-9 plus float32 rounding), each action is
    the team call's on the simulator's rows (the same policy, state carried) within 1e-5, and each command is the
    dynamics' command of that action; the episode reaches the goal.

    The one field a robot cannot know exactly is the previous reward's collision term: the observer takes the gap to
    the nearest obstacle from the nearest lidar reading, the simulator from its map (:mod:`~sb3_formation.ros.observer`),
    so the term can differ where an obstacle's nearest point lies between two rays at about d_safe: such steps differ
    by the term's value, r_o, and are rare (at most 2 % of the agent-steps)."""
    policy = SafePolicy(ShrinkingController(config))
    env = FormationEnv(config)
    observations = np.stack(list(env.reset(seed=0)[0].values()))
    rows, layout, model = env.engine.team_rows(env.team), env.observation_layout, dynamics_model(config)
    onboards = [Onboard(policy, AgentSettings(agent=agent)) for agent in range(config.n_agents)]
    increment = 2.0 * math.pi / config.lidar_rays
    far = config.agent_radius + config.lidar_range
    lidar = [layout["lidar_obstacles"], layout["lidar_agents"]]
    state, ended, steps, gap_terms = None, False, 0, 0
    while not ended:
        engine = env.engine
        positions, velocities = engine.latest.positions[rows].copy(), engine.latest.velocities[rows].copy()
        headings = engine.dynamics.headings_of(rows)
        headings = np.zeros(config.n_agents) if headings is None else headings.copy()
        speeds = engine.dynamics.forward_speeds_of(rows)
        speeds = np.zeros(config.n_agents) if speeds is None else speeds.copy()
        scans = merged_scan(engine.lidars[env.team], positions, stopped_by_agents=False)
        expected, state = policy.predict(observations, state, np.full(config.n_agents, steps == 0))
        actions = np.empty((config.n_agents, 2))
        for agent, onboard in enumerate(onboards):
            scan = Scan(scans[agent], -float(headings[agent]), increment, 0.0, far + 1.0)  # in the robot's frame
            done = onboard.step(scan, TeamView(positions, velocities, headings), float(speeds[agent]), env.goal)
            where = f"agent {agent} at step {steps}"
            for name, part in layout.items():
                if name == "previous_reward" and abs(done.row[part][0] - observations[agent, part][0]) > 1e-6:
                    assert abs(done.row[part][0] - observations[agent, part][0]) == pytest.approx(abs(config.r_o)), where
                    gap_terms += 1
                    continue
                tolerance = 1e-6 if part in lidar else 1e-9
                np.testing.assert_allclose(
                    done.row[part], observations[agent, part], rtol=2**-24, atol=tolerance, err_msg=f"{name} of {where}"
                )
            np.testing.assert_allclose(done.action, expected[agent], rtol=0, atol=1e-5, err_msg=where)
            np.testing.assert_array_equal(done.command, model.command(done.action, velocities[agent], speeds[agent]))
            assert done.message.shape == (0,)
            actions[agent] = done.action
        observations, _, terminated, truncated, infos = env.step_array(actions)
        ended, steps = terminated or truncated, steps + 1
    assert terminated and infos[0]["success"] and steps == 500
    assert gap_terms <= 0.02 * steps * config.n_agents, gap_terms


def test_a_new_goal_starts_a_new_episode_on_board() -> None:
    """After :meth:`Onboard.reset` the pipeline acts as a fresh one: same row (time step 0, no previous action) and the
    same action for the same inputs."""
    env = FormationEnv(STAGE_3)
    env.reset(seed=1)
    rows = env.engine.team_rows(env.team)
    positions, velocities = env.engine.latest.positions[rows], env.engine.latest.velocities[rows]
    team = TeamView(positions, velocities, np.zeros(6))
    scan = Scan(merged_scan(env.engine.lidars[env.team], positions, False)[0], 0.0, 2 * math.pi / 90, 0.0, 3.0)
    onboard = Onboard(ShrinkingController(STAGE_3), AgentSettings(agent=0))
    first = onboard.step(scan, team, 0.0, env.goal)
    later = onboard.step(scan, team, 0.0, env.goal)
    assert later.row[onboard.observer.layout["time_step"]] == 1 and not onboard.starting
    onboard.reset()
    again = onboard.step(scan, team, 0.0, env.goal)
    np.testing.assert_array_equal(again.row, first.row)
    np.testing.assert_array_equal(again.action, first.action)


def test_the_filter_setting_puts_the_policy_behind_the_filter_or_strips_it() -> None:
    """``safety_filter`` on: the policy is behind the filter, a policy already behind one keeps its gains; off: an
    export's filter is stripped (the one rule, :func:`~sb3_formation.safety.policy.with_filter`)."""
    controller = ShrinkingController(STAGE_3)
    assert isinstance(Onboard(controller, AgentSettings()).policy, SafePolicy)
    assert Onboard(controller, AgentSettings(safety_filter=False)).policy is controller
    shielded = SafePolicy(controller)
    kept = Onboard(shielded, AgentSettings()).policy
    assert isinstance(kept, SafePolicy) and kept.filter.gains == shielded.filter.gains and kept.policy is controller
    assert Onboard(shielded, AgentSettings(safety_filter=False)).policy is controller


def test_the_agent_node_holds_no_observation_filter_or_policy_logic() -> None:
    """The rclpy node imports, of the package, only the message conversions, the on-board module and the policy
    contract's type: the observer, the scans, the filter, the runtime and the dynamics are the on-board module's."""
    tree = ast.parse((PACKAGE / "ros" / "agent_node.py").read_text())
    imported = {
        node.module
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("sb3_formation")
    }
    assert imported == {"sb3_formation.controllers.base", "sb3_formation.ros.messages", "sb3_formation.ros.onboard"}
    allowed = {"TeamPolicy"}
    from_base = {
        alias.name
        for node in ast.walk(tree)
        if isinstance(node, ast.ImportFrom) and node.module == "sb3_formation.controllers.base"
        for alias in node.names
    }
    assert from_base <= allowed


def test_the_latency_benchmark_measures_the_module_the_node_runs() -> None:
    """benchmarks/ros_latency.py's reference is :class:`Onboard`, built from the node's settings, not a copy."""
    source = (PACKAGE.parents[1] / "benchmarks" / "ros_latency.py").read_text()
    assert "Onboard(load_onnx_policy(MODEL, threads=1), AgentSettings(agent=AGENT))" in source
    for copied in ("resample_scan(", "split_scan(", "AgentObserver(", "SafetyFilter(", ".agent_step("):
        assert copied not in source, copied


class Broken:
    """A policy that answers every observation with a NaN action (the on-board checks must not rely on the policy's)."""

    def __init__(self, config: FormationConfig) -> None:
        self.config, self.message_size = config, 0

    def agent_step(self, observation, agents, state, episode_start, received=None):
        return np.full((len(agents), 2), np.nan, dtype=np.float32), state, np.zeros((len(agents), 0), dtype=np.float32)


def test_unusable_inputs_and_non_finite_results_are_refused_before_and_after_the_policy() -> None:
    """:meth:`Onboard.check` names, in one line, a NaN or huge position, a NaN velocity, a NaN goal, a scan of too
    many ranges (before any work) and a scan with NaN angles; a policy's NaN action is refused after the step and the
    robot's memory is as before (the next step is still the episode's first)."""
    from sb3_formation.ros.onboard import MAX_SCAN_RANGES, UnusableInput, command_problem, typed_parameters

    env = FormationEnv(STAGE_3)
    env.reset(seed=1)
    rows = env.engine.team_rows(env.team)
    positions, velocities = env.engine.latest.positions[rows].copy(), env.engine.latest.velocities[rows].copy()
    scan = Scan(merged_scan(env.engine.lidars[env.team], positions, False)[0], 0.0, 2 * math.pi / 90, 0.0, 3.0)
    onboard = Onboard(ShrinkingController(STAGE_3), AgentSettings(agent=0, safety_filter=False))
    team = TeamView(positions, velocities, np.zeros(6))
    onboard.check(scan, team, 0.0, env.goal)
    bad_positions, bad_velocities = positions.copy(), velocities.copy()
    bad_positions[2, 0], bad_velocities[0, 1] = np.nan, np.nan
    huge = positions.copy()
    huge[4] = 1e9
    cases = [
        ((scan, TeamView(bad_positions, velocities, np.zeros(6)), 0.0, env.goal), "odometry of agent 2: agent 2's position"),
        ((scan, TeamView(huge, velocities, np.zeros(6)), 0.0, env.goal), "is not a finite point within 100000 m"),
        ((scan, TeamView(positions, bad_velocities, np.zeros(6)), 0.0, env.goal), "odometry of agent 0: velocity"),
        ((scan, team, 0.0, np.array([np.nan, 1.0])), "the goal [nan, 1.0] is not a finite point"),
        ((scan._replace(ranges=np.zeros(MAX_SCAN_RANGES + 1)), team, 0.0, env.goal), f"a scan of {MAX_SCAN_RANGES + 1}"),
        ((scan._replace(angle_increment=math.nan), team, 0.0, env.goal), "the scan's angles are not finite"),
        ((scan._replace(range_max=math.nan), team, 0.0, env.goal), "the scan's limits admit no range"),
    ]
    for arguments, message in cases:
        with pytest.raises(UnusableInput, match=re.escape(message)):
            onboard.step(*arguments)
    assert onboard.starting and onboard.observer.step == 0
    broken = Onboard(Broken(STAGE_3), AgentSettings(agent=0, safety_filter=False))
    with pytest.raises(UnusableInput, match="the policy gave a non-finite action"):
        broken.step(scan, team, 0.0, env.goal)
    assert broken.starting and broken.observer.memory()[0] == 0 and not broken.observer.previous_action.any()
    assert command_problem([0.0, math.inf, 0, 0, 0, 0]) and not command_problem([0.1] * 6)
    defaults = AgentSettings()
    values = {item: getattr(defaults, item) for item in AgentSettings.__dataclass_fields__}
    assert typed_parameters(defaults, values | {"input_timeout": 2})["input_timeout"] == 2.0
    with pytest.raises(ValueError, match=re.escape("parameter agent must be an integer, got 1.5")):
        typed_parameters(defaults, values | {"agent": 1.5})
