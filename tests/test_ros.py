"""The ROS 2 nodes over real rclpy publishers and subscribers (``docs/deployment.md``): ``make test-ros`` runs these in
the ROS environment (``.venv-ros``); elsewhere they are skipped.

Every test process keeps discovery on this machine and takes a ROS domain of its own (one per pytest-xdist worker).
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytestmark = pytest.mark.ros
rclpy = pytest.importorskip("rclpy", reason="the ROS 2 tests run in the ros environment: make test-ros")

from geometry_msgs.msg import PointStamped, Twist  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import JointState, LaserScan  # noqa: E402
from std_msgs.msg import Float32MultiArray  # noqa: E402

from sb3_formation.env.observations import observation_fields, observation_layout  # noqa: E402
from sb3_formation.env.sensors import ray_directions  # noqa: E402
from sb3_formation.ros.agent_node import GOAL_QOS, AgentNode, AgentSettings  # noqa: E402
from sb3_formation.ros.messages import (  # noqa: E402
    goal_message,
    odometry_message,
    policy_message,
    policy_message_of,
    stamp_of,
)
from sb3_formation.runtime import OnnxPolicy  # noqa: E402
from sb3_formation.safety.policy import SafePolicy  # noqa: E402

PRETRAINED = Path(__file__).resolve().parents[1] / "src" / "sb3_formation" / "pretrained"
MODEL = PRETRAINED / "ch5-bearing" / "final_model.onnx"


@pytest.fixture(scope="module", autouse=True)
def local_ros() -> None:
    """Discovery on this machine only."""
    os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"


#: Domains per pytest-xdist worker: one per test that takes a context, and the last for the command-line team.
WORKER_DOMAINS = 40
DOMAINS = iter(range(WORKER_DOMAINS - 1))


@pytest.fixture
def context() -> Iterator[rclpy.context.Context]:
    """A fresh rclpy context per test, in a domain of its own (no latched goal of another test reaches it)."""
    worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0)
    os.environ["ROS_DOMAIN_ID"] = str(100 + WORKER_DOMAINS * worker + next(DOMAINS))
    context = rclpy.context.Context()
    rclpy.init(context=context)
    yield context
    rclpy.try_shutdown(context=context)


@pytest.fixture(scope="module")
def policy() -> OnnxPolicy:
    return OnnxPolicy(MODEL, threads=1)


def spin_until(executor: SingleThreadedExecutor, done: Callable[[], bool], timeout: float = 20.0) -> None:
    """Spin until ``done()``; fail after ``timeout`` wall-clock seconds (a hang guard)."""
    deadline = time.monotonic() + timeout
    while not done():
        assert time.monotonic() < deadline, "timed out waiting over ROS 2"
        executor.spin_once(timeout_sec=0.05)


class TeamFeed:
    """A test node that plays a team's odometry, the goal and agent 0's scan, and listens to agent 0's command and
    observation."""

    def __init__(self, context: rclpy.context.Context, n_agents: int) -> None:
        self.node = Node("team_feed", context=context)
        self.odometry = [self.node.create_publisher(Odometry, f"/agent_{index}/odom", 10) for index in range(n_agents)]
        self.scan = self.node.create_publisher(LaserScan, "/agent_0/scan", 10)
        self.goal = self.node.create_publisher(PointStamped, "/goal", GOAL_QOS)
        self.commands: list[Twist] = []
        self.observations: list[np.ndarray] = []
        self.node.create_subscription(Twist, "/agent_0/cmd_vel", self.commands.append, 10)
        self.node.create_subscription(
            Float32MultiArray, "/agent_0/observation", lambda message: self.observations.append(np.array(message.data)), 10
        )

    def publish(
        self, seconds: float, positions: np.ndarray, yaw: float, scan: LaserScan | None, goal: np.ndarray | None
    ) -> None:
        """One instant: every agent's odometry (at rest; agent 0 heading ``yaw``), the goal, agent 0's scan."""
        stamp = stamp_of(seconds)
        for index, publisher in enumerate(self.odometry):
            heading = yaw if index == 0 else 0.0
            publisher.publish(
                odometry_message(stamp, ("map", f"agent_{index}/base_link"), positions[index], heading, np.zeros(2), 0.0)
            )
        if goal is not None:
            self.goal.publish(goal_message(stamp_of(0.0), "map", goal))
        if scan is not None:
            scan.header.stamp = stamp
            self.scan.publish(scan)


def stopped(process: subprocess.Popen, number: int) -> str:
    """Send ``number`` to ``process`` (the parent only) and return its output once it ends; if it has not ended within
    60 s, kill its whole process group (no agent is left running) and fail."""
    process.send_signal(number)
    try:
        return str(process.communicate(timeout=60)[0])
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.communicate()
        raise


def hand_scan(ranges: np.ndarray, angle_min: float, increment: float, range_max: float = 30.0) -> LaserScan:
    """A ``LaserScan`` of ``ranges`` (m), beam k at ``angle_min + k increment`` (rad) in agent 0's base frame."""
    message = LaserScan()
    message.header.frame_id = "agent_0/base_link"
    message.angle_min, message.angle_increment = angle_min, increment
    message.angle_max = angle_min + increment * (len(ranges) - 1)
    message.range_min, message.range_max = 0.05, range_max
    message.ranges = [float(value) for value in ranges]
    return message


def wall_ranges(angles_world: np.ndarray, distance: float) -> np.ndarray:
    """Ranges (m) from the origin to the wall x = ``distance`` along world angles (rad): d / cos, inf facing away."""
    cos = np.cos(angles_world)
    return np.where(cos > 1e-9, distance / np.where(cos > 1e-9, cos, 1.0), np.inf)


#: Agent 0 at (5, 5); its teammates far enough that none is within its lidar's reach.
TEAM = np.array([[5.0, 5.0], [9.0, 1.0], [13.0, 1.0], [13.0, 9.0], [9.0, 9.0], [1.0, 9.0]])


def observed_obstacles(feed: TeamFeed, policy: OnnxPolicy) -> np.ndarray:
    layout = observation_layout(observation_fields(policy.config))
    return feed.observations[-1][layout["lidar_obstacles"]]


def expected_wall(policy: OnnxPolicy, distance: float, covered: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """The obstacle channel a wall x = 5 + ``distance`` gives agent 0, by hand: along task ray k at world angle
    theta_k, d / cos(theta_k) - R_a within range, 1 elsewhere and where ``covered`` is False."""
    config = policy.config
    angles = np.arctan2(*ray_directions(config.lidar_rays)[:, ::-1].T)
    surface = wall_ranges(angles, distance) - config.agent_radius
    readings = np.where((surface <= config.lidar_range) & covered(angles), np.maximum(surface, 0.0), config.lidar_range)
    return readings / config.lidar_range


@pytest.mark.parametrize(
    ("increment_deg", "angle_min_deg", "beams", "yaw_deg", "covered"),
    [
        (1.0, 0.0, 360, 0.0, lambda angles: np.ones_like(angles, dtype=bool)),  # 4 x the task's resolution
        (0.7, -180.0, 515, 0.0, lambda angles: np.ones_like(angles, dtype=bool)),  # rays between beams: the segments
        (0.25, -135.0, 1081, 0.0, lambda angles: np.abs(angles) <= math.radians(135.0)),  # a 270 deg scanner
        (1.0, 0.0, 360, 90.0, lambda angles: np.ones_like(angles, dtype=bool)),  # the robot turned: a rotated frame
        (-0.5, 180.0, 720, 30.0, lambda angles: np.ones_like(angles, dtype=bool)),  # clockwise, another yaw
    ],
)
def test_the_node_resamples_hand_made_scans(context, policy, increment_deg, angle_min_deg, beams, yaw_deg, covered) -> None:
    """A flat wall 1 m ahead, scanned at another resolution, angle range, direction or robot heading, reaches the
    observation as the task's rays would see it (computed by hand)."""
    node = AgentNode(
        policy, AgentSettings(agent=0, synchronous=True, observation_topic="observation"), namespace="agent_0", context=context
    )
    feed = TeamFeed(context, policy.config.n_agents)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.add_node(feed.node)
    yaw = math.radians(yaw_deg)
    beam_angles = math.radians(angle_min_deg) + math.radians(increment_deg) * np.arange(beams)
    scan = hand_scan(wall_ranges(beam_angles + yaw, 1.0), math.radians(angle_min_deg), math.radians(increment_deg))
    feed.publish(1.0, TEAM, yaw, scan, np.array([12.0, 5.0]))
    spin_until(executor, lambda: bool(feed.observations))
    np.testing.assert_allclose(observed_obstacles(feed, policy), expected_wall(policy, 1.0, covered), atol=2e-6)
    executor.shutdown()


class FreeRun:
    """Agent 0 free-running (``input_timeout`` 1 s) beside a :class:`TeamFeed` that plays its inputs in real time."""

    def __init__(self, context: rclpy.context.Context, policy: OnnxPolicy) -> None:
        # the one node of the team: its teammates, never heard, do not fail (failed_after has tests of its own)
        settings = AgentSettings(agent=0, input_timeout=1.0, watchdog_rate=20.0, failed_after=0.0)
        self.node = AgentNode(policy, settings, namespace="agent_0", context=context)
        self.feed = TeamFeed(context, policy.config.n_agents)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.feed.node)
        rays = policy.config.lidar_rays
        self.scan = hand_scan(np.full(rays, np.inf), 0.0, 2 * math.pi / rays)

    def play(
        self, seconds: float, with_scan: bool, goal: np.ndarray | None, each_instant: Callable[[Any], None] | None = None
    ) -> list[Twist]:
        """The commands agent 0 sent while the feed played for ``seconds`` (``each_instant`` called with each stamp)."""
        self.feed.commands.clear()
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            stamp = self.node.get_clock().now().nanoseconds / 1e9
            self.feed.publish(stamp, TEAM, 0.0, self.scan if with_scan else None, goal)
            if each_instant is not None:
                each_instant(stamp_of(stamp))
            for _ in range(20):  # every message of the instant, and the node's command
                self.executor.spin_once(timeout_sec=0.002)
        return list(self.feed.commands)


def moving(commands: list[Twist]) -> bool:
    return any(abs(command.linear.x) + abs(command.linear.y) > 0 for command in commands)


def zero(commands: list[Twist]) -> bool:
    return bool(commands) and all(command.linear.x == command.linear.y == command.angular.z == 0.0 for command in commands)


def test_a_stale_or_missing_input_stops_the_agent(context, policy) -> None:
    """Free-running: with every input fresh the agent moves; no goal, a teammate's odometry missing, or no scan for
    ``input_timeout`` gives zero commands (and the node keeps running)."""
    run = FreeRun(context, policy)
    first = run.play(1.5, True, None)
    assert zero(first), f"no goal yet: the agent must stand still, got {first}"
    goal = np.array([12.0, 5.0])
    fresh = run.play(2.0, True, goal)
    assert moving(fresh), f"every input fresh: the agent must move towards the goal, got {fresh[:3]}"
    later = run.play(3.0, False, goal)  # the scan stops
    assert zero(later[-5:]), "no scan for input_timeout: the agent must stop"
    run.feed.odometry[3] = run.feed.node.create_publisher(Odometry, "/agent_3/unused", 10)  # agent 3's odometry stops
    assert zero(run.play(3.0, True, goal)[-5:]), "a teammate's odometry missing: the agent must stop"
    run.executor.shutdown()


def test_a_silent_neighbour_stops_a_talking_agent(context, tmp_path) -> None:
    """Free-running with a policy whose agents send messages: agent 0 moves while its ring neighbours 5 and 1 talk,
    publishes its own message, and stops once agent 1 has been silent for ``input_timeout``."""
    from test_messages import untrained

    from sb3_formation.env.config import FormationConfig
    from sb3_formation.sb3.onnx_export import export_onnx

    model = export_onnx(untrained(FormationConfig.task("ch5-bearing", stage=3), True, 4), tmp_path / "talk.onnx")
    run = FreeRun(context, OnnxPolicy(model, threads=1))
    neighbours = {index: run.feed.node.create_publisher(JointState, f"/agent_{index}/message", 10) for index in (5, 1)}
    sent: list[np.ndarray] = []
    run.feed.node.create_subscription(JointState, "/agent_0/message", lambda message: sent.append(message.position), 10)

    def talk(speakers: tuple[int, ...]) -> Callable[[Any], None]:
        return lambda stamp: [neighbours[index].publish(policy_message(stamp, np.full(4, 0.5))) for index in speakers]

    goal = np.array([12.0, 5.0])
    assert moving(run.play(2.0, True, goal, talk((5, 1)))), "every input fresh: the agent must move"
    assert sent and len(sent[-1]) == 4
    assert zero(run.play(3.0, True, goal, talk((5,)))[-5:]), "agent 1 silent for input_timeout: the agent must stop"
    run.executor.shutdown()


#: (s) the agents' input_timeout where a test holds the synchronous loop to evaluation: a simulator starved of the CPU for
#: input_timeout (a loaded machine) gets the agents' watchdog zeros as commands (docs/deployment.md), which this test
#: is not about; the watchdog has tests of its own
LOCKSTEP_TIMEOUT = 60.0


def fly(
    context: rclpy.context.Context,
    model: Path | Any,
    episodes: int,
    see_through: bool,
    observe: bool = False,
    extra_nodes: list[Node] | None = None,
    heard: Callable[[int], bool] | None = None,
    disturbances: str = "ideal",
    stage: int = 3,
) -> tuple:
    """The simulator node and a team's agent nodes (and ``extra_nodes``) in one executor, synchronous, filter on: the
    simulator's episode records, the env's observation rows of every step, and each agent's published observations
    (with ``observe``). After the last step it spins until ``heard(steps)`` holds too (what ``extra_nodes`` listen to
    may still be on its way). Under ``disturbances`` the simulator applies them and the agents' filters declare their
    bounds from them. ``model``: an exported file, or a policy (the task its config's)."""
    from sb3_formation.ros.sim_node import SimNode, SimSettings

    policy = OnnxPolicy(model, threads=1) if isinstance(model, Path) else model
    config = policy.config.replace(stage=stage)
    settings = SimSettings(
        seed=0, episodes=episodes, see_through_agents=see_through, command_timeout=120.0, disturbances=disturbances
    )
    sim = SimNode(config, settings, context=context)
    rows: list[np.ndarray] = []
    original_reset, original_step = sim.env.reset, sim.env.step_array

    def reset(**kwargs):  # the env's rows, as agent 0 should observe them
        observations, infos = original_reset(**kwargs)
        rows.append(np.stack([observations[agent] for agent in sim.env.agents]))
        return observations, infos

    def step_array(actions):
        stepped = original_step(actions)
        rows.append(stepped[0].copy())
        return stepped

    sim.env.reset, sim.env.step_array = reset, step_array
    agents = [
        AgentNode(
            policy,
            AgentSettings(
                agent=index,
                synchronous=True,
                observation_topic="observation" if observe else "",
                input_timeout=LOCKSTEP_TIMEOUT,
                filter_disturbances="" if disturbances == "ideal" else disturbances,
            ),
            name=f"agent_{index}",
            namespace=f"agent_{index}",
            context=context,
        )
        for index in range(config.n_agents)
    ]
    observed: list[list[np.ndarray]] = [[] for _ in range(config.n_agents)]
    listener = Node("listener", context=context)
    for index, seen in enumerate(observed):
        topic = f"/agent_{index}/observation"
        listener.create_subscription(
            Float32MultiArray, topic, lambda message, seen=seen: seen.append(np.array(message.data)), 5000
        )
    executor = SingleThreadedExecutor(context=context)
    for node in [sim, *agents, listener, *(extra_nodes or [])]:
        executor.add_node(node)
    spin_until(executor, lambda: sim.done, timeout=600.0)
    steps = sum(record.steps for record in sim.results)
    spin_until(executor, lambda: not observe or all(len(seen) >= steps for seen in observed), timeout=60.0)
    spin_until(executor, lambda: heard is None or heard(steps), timeout=60.0)
    executor.shutdown()
    return sim.results, rows, observed, config


def stopped_by_teammates(positions: np.ndarray, config) -> np.ndarray:
    """The task rays of the agent in row 0 that meet a teammate's disc within the lidar's reach, by hand: a ray u from
    p_0 meets the disc round p_j where |p_0 + t u - p_j| = R_a has a root t in [0, R_a + range] (the range counts from
    its surface)."""
    angles = 2 * np.pi * np.arange(config.lidar_rays) / config.lidar_rays
    rays = np.stack([np.cos(angles), np.sin(angles)], axis=1)
    offsets = positions[1:] - positions[0]  # (n - 1, 2)
    along = rays @ offsets.T  # (rays, n - 1)
    discriminant = along**2 - (np.sum(offsets**2, axis=1) - config.agent_radius**2)
    root = np.sqrt(np.maximum(discriminant, 0.0))
    meets = (discriminant >= 0) & (along + root >= 0) & (along - root <= config.agent_radius + config.lidar_range)
    return meets.any(axis=1)


def evaluated(model: Path | Any, episodes: int, disturbances: str = "ideal", stage: int = 3):
    """The same episodes evaluated in process (``sb3-formation evaluate safe:onnx:<model> --disturbances ...``'s
    loop); ``model``: an exported file, or a policy."""
    from sb3_formation.env.disturbances import load_disturbances
    from sb3_formation.experiment.evaluation import evaluate

    overrides = {"disturbances": load_disturbances(disturbances)}
    policy = SafePolicy(OnnxPolicy(model, threads=1) if isinstance(model, Path) else model)
    return evaluate(policy, episodes, stage=stage, seed=0, n_envs=episodes, record=episodes, env_overrides=overrides)


def largest_difference(record, trajectories, episode: int) -> float:
    """The largest distance (m) between an agent's position over ROS 2 and in process, over the steps both played."""
    common = min(record.steps, int(trajectories.lengths[episode])) + 1
    return float(np.linalg.norm(record.positions[:common] - trajectories.positions[episode, :common], axis=-1).max())


@pytest.mark.parametrize(("name", "tolerance"), [("ch5-bearing", 1e-6), ("ch5-bearing-unicycle", 1e-4)])
def test_with_scans_that_see_through_agents_the_loop_is_evaluation(context, name, tolerance) -> None:
    """When the scans see what the simulator's lidar sees, the closed loop over ROS 2 flies the evaluation's episodes:
    same outcomes and steps, positions within ``tolerance``: only the scans' float32 ranges differ, which a unicycle's
    turns amplify to tens of micrometres over an episode (docs/deployment.md)."""
    model = PRETRAINED / name / "final_model.onnx"
    results, _, _, _ = fly(context, model, episodes=1, see_through=True)
    reference = evaluated(model, 1)
    assert [(r.success, r.steps) for r in results] == [(row["success"], row["length"]) for row in reference.episodes]
    assert largest_difference(results[0], reference.trajectories, 0) <= tolerance


def test_among_a_crowd_the_loop_is_evaluation(context) -> None:
    """In the crowd family (walkers that react to the agents, moved by the simulator's engine; that its scans hold
    them is tests/test_movers.py's), with scans that see through agents a team of shrinking-controller nodes flies the
    evaluation's episode (its first 600 steps, among the walkers): same steps, positions within 1e-5 m (the scans'
    float32 ranges, which the walkers' reactions to the agents carry on)."""
    from sb3_formation.controllers.shrinking import ShrinkingController
    from sb3_formation.env.config import FormationConfig

    config = FormationConfig.task("ch5-bearing", stage=3).replace(scenes="crowd", max_steps=600)
    policy = ShrinkingController(config)
    results, _, _, _ = fly(context, policy, episodes=1, see_through=True)
    reference = evaluated(policy, 1)
    assert [(r.success, r.steps) for r in results] == [(row["success"], row["length"]) for row in reference.episodes]
    assert largest_difference(results[0], reference.trajectories, 0) <= 1e-5


def test_a_killed_agent_node_fails_and_its_teammates_re_form_and_reach_the_goal(context) -> None:
    """Six shrinking-controller nodes fly a stage-3 episode; agent 2's node is destroyed after 30 steps. The simulator
    hears no command from it for ``failed_after`` and stops its motors (the engine's failure: a passive body on the
    others' obstacle channel); the others hear its messages stop and re-form the ring of 5 without it (0-1-3-4-5), and
    the five reach the goal."""
    from sb3_formation.controllers.shrinking import ShrinkingController
    from sb3_formation.env.config import FormationConfig
    from sb3_formation.ros.sim_node import SimNode, SimSettings

    config = FormationConfig.task("ch5-bearing", stage=3)
    policy = ShrinkingController(config)
    settings = SimSettings(seed=0, episodes=1, command_timeout=120.0, failed_after=1.0)
    sim = SimNode(config, settings, context=context)
    agents = [
        AgentNode(
            policy,
            AgentSettings(agent=index, synchronous=True, input_timeout=LOCKSTEP_TIMEOUT, failed_after=1.0),
            name=f"agent_{index}",
            namespace=f"agent_{index}",
            context=context,
        )
        for index in range(config.n_agents)
    ]
    executor = SingleThreadedExecutor(context=context)
    for node in [sim, *agents]:
        executor.add_node(node)
    spin_until(executor, lambda: sim.env.step_count >= 30, timeout=300.0)
    executor.remove_node(agents[2])
    agents[2].destroy_node()
    spin_until(executor, lambda: sim.done, timeout=600.0)
    executor.shutdown()
    assert sim.failed.tolist() == [False, False, True, False, False, False]
    (record,) = sim.results
    assert record.success, "the five that fly must reach the goal"
    kept = record.positions[32:, 2]
    assert np.linalg.norm(kept - kept[-1], axis=1).max() < 0.05, "agent 2 stands where it stopped (pushed at most)"
    for index in (0, 1, 3, 4, 5):
        onboard = agents[index].onboard
        assert onboard.flying.tolist() == [True, True, False, True, True, True]
        assert onboard.observer.neighbours[1].tolist() == [0, 3] and onboard.observer.neighbours[3].tolist() == [1, 4]


def test_a_real_scanner_splits_into_the_simulators_channels_and_flies_the_same_episodes(context) -> None:
    """With scans that agents stop (a real scanner), each agent's observation over ROS 2 holds the simulator's agent
    channel exactly and its obstacle channel on every ray no teammate stops (1 on those a teammate stops), every other
    field but the previous action as the simulator's; the episodes end as in evaluation, within 5 steps of its lengths,
    their positions within 0.05 m (the measured drift of 20 episodes is in docs/deployment.md)."""
    results, rows, observed, config = fly(context, MODEL, episodes=2, see_through=False, observe=True)
    reference = evaluated(MODEL, 2)
    assert [r.success for r in results] == [row["success"] for row in reference.episodes]
    assert all(abs(r.steps - row["length"]) <= 5 for r, row in zip(results, reference.episodes))
    assert max(largest_difference(record, reference.trajectories, k) for k, record in enumerate(results)) <= 0.05
    layout = observation_layout(observation_fields(config))
    obstacles, agents = layout["lidar_obstacles"], layout["lidar_agents"]
    shadowed_rays = 0
    for agent, seen_rows in enumerate(observed):
        simulated, teams = [], []
        for k, record in enumerate(results):  # each episode's rows before its last step: what the agents acted on
            first = int(sum(r.steps + 1 for r in results[:k]))
            simulated += [rows[first + t][agent] for t in range(record.steps)]
            teams += list(np.roll(record.positions[: record.steps], -agent, axis=1))  # the agent first
        assert len(simulated) == len(seen_rows)
        for seen, truth, team in zip(seen_rows, simulated, teams):
            np.testing.assert_allclose(seen[agents], truth[agents], atol=1e-6)
            others = np.ones(len(seen), dtype=bool)
            # the simulator's row holds the action it recovered from the command, which differs from the policy's (the
            # one the node remembers, and training saw) where the speed limit cut the command
            others[obstacles] = others[agents] = others[layout["previous_action"]] = False
            np.testing.assert_allclose(seen[others], truth[others], rtol=1e-6, atol=1e-6)
            differs = np.abs(seen[obstacles] - truth[obstacles]) > 1e-6
            assert np.all(seen[obstacles][differs] == 1.0), "a ray that differs must read nothing"
            assert not np.any(differs & ~stopped_by_teammates(team, config)), "a ray that differs must be one a teammate stops"
            shadowed_rays += int(differs.sum())
    assert shadowed_rays > 0, "the episodes must include obstacles behind teammates, or this test checks nothing of them"


def test_a_policy_with_messages_talks_to_its_neighbours_over_ros_as_in_evaluation(context, tmp_path) -> None:
    """A policy whose agents send messages of 4 values (untrained, its layers scaled so that the messages move the
    actions): over ROS 2 each agent publishes one message per step on its topic and acts on its two neighbours'
    messages of the step before, so the closed loop flies the evaluation's episode (scans that see through agents:
    positions within 1e-5 m); the same loop with the messages zeroed in process flies another."""
    from test_messages import untrained

    from sb3_formation.env.config import FormationConfig
    from sb3_formation.experiment.evaluation import evaluate
    from sb3_formation.sb3.onnx_export import export_onnx

    model = export_onnx(untrained(FormationConfig.task("ch5-bearing", stage=3, max_steps=60), True, 3), tmp_path / "talk.onnx")
    heard: list[tuple[int, np.ndarray]] = []
    listener = Node("message_listener", context=context)
    listener.create_subscription(
        JointState, "/agent_0/message", lambda message: heard.append(policy_message_of(message)), 1000
    )
    results, _, _, _ = fly(
        context, model, episodes=1, see_through=True, extra_nodes=[listener], heard=lambda steps: len(heard) >= steps
    )
    reference = evaluated(model, 1)
    assert [(r.success, r.steps) for r in results] == [(row["success"], row["length"]) for row in reference.episodes]
    assert largest_difference(results[0], reference.trajectories, 0) <= 1e-5
    stamps = [stamp for stamp, _ in heard]
    assert len(heard) == results[0].steps == 60 and stamps == sorted(stamps) and heard[0][1].shape == (4,)
    assert max(float(np.abs(values).max()) for _, values in heard) > 0.1

    class Deaf:  # the same policy with every received message zeroed
        def __init__(self, policy: OnnxPolicy) -> None:
            self.policy, self.config = policy, policy.config

        def fit(self, config):
            return self

        def predict(self, observation, state=None, episode_start=None, deterministic=True, *, channel=None):
            if state is not None:
                state = (state[0], np.zeros_like(state[1]))
            return self.policy.predict(observation, state, episode_start, deterministic, channel=channel)

    deaf = evaluate(SafePolicy(Deaf(OnnxPolicy(model, threads=1))), 1, stage=3, seed=0, n_envs=1, record=1)
    assert largest_difference(results[0], deaf.trajectories, 0) > 1e-3


#: Stage-2 episodes of the shipped policy at ``realistic`` last about 700-800 steps: three of them fit a test's time
#: (about 2 minutes beside the other tests on 2 cores); the benchmark measures 20 (docs/deployment.md).
REALISTIC_EPISODES = 3


def test_at_realistic_the_loop_ends_its_episodes_as_evaluation_does(context) -> None:
    """The simulator node at ``realistic`` (noisy odometry and scans, observation delays, motor errors and action delays
    in its engine) and agents whose filters declare the same bounds fly stage-2 episodes (a real scanner) that end as
    evaluation's at ``realistic`` do, seed for seed: the same outcome, and a length within 10 %, in at least 90 % of
    them (docs/deployment.md: what parts the two, and the benchmark's 20 episodes)."""
    results, _, _, _ = fly(context, MODEL, REALISTIC_EPISODES, see_through=False, disturbances="realistic", stage=2)
    reference = evaluated(MODEL, REALISTIC_EPISODES, "realistic", stage=2)
    alike = [
        record.success == row["success"] and abs(record.steps - row["length"]) <= 0.1 * row["length"]
        for record, row in zip(results, reference.episodes, strict=True)
    ]
    outcomes = [(r.success, r.steps, row["success"], row["length"]) for r, row in zip(results, reference.episodes)]
    assert sum(alike) >= 0.9 * REALISTIC_EPISODES, outcomes
    assert any(row["success"] for row in reference.episodes), "the episodes must include successes"


def realistic_env(config, seed: int):
    """A stage-3 env of ``config`` at ``realistic``, reset at ``seed``, and its team's rows."""
    from sb3_formation.env.formation_env import FormationEnv

    env = FormationEnv(config.replace(stage=3, disturbances="realistic"))
    env.reset(seed=seed)
    return env, env.engine.team_rows(env.team)


@pytest.mark.parametrize("dynamics", ["holonomic", "unicycle"])
def test_the_published_odometry_and_scans_hold_what_the_engine_sensed(dynamics: str) -> None:
    """At ``realistic``, each step's messages (built as the simulator node builds them, no node needed) read back, as
    an agent node reads them, to the engine's sensed values: the odometry's position is the estimate, its yaw the true
    heading plus the heading error, its velocity the estimate; the scan, resampled with that yaw, is the engine's
    obstacle channel with its heading turn, range errors and dropped beams (within float32 rounding)."""
    from sb3_formation.env.config import FormationConfig
    from sb3_formation.env.sensors import OBSTACLE_CHANNEL
    from sb3_formation.ros.messages import odometry_state, scan_message, scan_of
    from sb3_formation.ros.scans import ScanMount, resample_scan
    from sb3_formation.ros.sensing import published_team

    env, rows = realistic_env(FormationConfig.task("ch5-bearing", dynamics=dynamics), seed=4)
    config, generator = env.config, np.random.default_rng(0)
    reach = (config.agent_radius, config.agent_radius + config.lidar_range)
    dropped = turned = 0
    for step in range(12):
        engine = env.engine
        sensed, lidar = engine.sensed, engine.episodes.lidar[OBSTACLE_CHANNEL]
        true_headings = engine.dynamics.headings_of(rows)
        team = published_team(engine, env.team, stopped_by_agents=False)
        for agent in range(config.n_agents):
            row, where = rows.start + agent, f"agent {agent} at step {step}"
            frames = ("map", f"agent_{agent}/base_link")
            message = odometry_message(
                stamp_of(step * config.dt),
                frames,
                team.positions[agent],
                float(team.headings[agent]),
                team.body_velocities[agent],
                0.0,
            )
            position, yaw, velocity = odometry_state(message)
            heading = (0.0 if true_headings is None else true_headings[agent]) + sensed.heading_errors[row]
            np.testing.assert_array_equal(position, sensed.positions[row], err_msg=where)
            assert abs(math.remainder(yaw - heading, 2 * math.pi)) < 1e-12, where
            np.testing.assert_allclose(velocity, sensed.velocities[row], rtol=0, atol=1e-15, err_msg=where)
            if dynamics == "unicycle":  # the forward speed the agent commands from: along the heading it is given
                forward = math.cos(heading) * sensed.velocities[row, 0] + math.sin(heading) * sensed.velocities[row, 1]
                assert message.twist.twist.linear.x == pytest.approx(forward, abs=1e-15), where
            scan = scan_of(
                scan_message(stamp_of(step * config.dt), frames[1], team.ranges[agent], float(team.scan_angles[agent]), *reach)
            )
            readings = resample_scan(scan, ScanMount(), yaw, config) / config.lidar_range
            np.testing.assert_allclose(readings, lidar[row], rtol=0, atol=2e-6, err_msg=where)
            assert np.isinf(np.asarray(scan.ranges)[sensed.dropped[row]]).all(), where
            dropped += int(sensed.dropped[row].sum())
            turned += abs(sensed.heading_errors[row]) > math.radians(0.5)
        env.step_array(generator.uniform(-1.0, 1.0, (config.n_agents, 2)))
    assert dropped > 0 and turned > 0, "the steps must drop beams and turn scans, or this test checks nothing of them"


def test_delayed_deliveries_give_the_engines_delayed_rows() -> None:
    """At ``realistic``, six on-board pipelines (the shipped policy behind a filter of realistic bounds), each fed what
    the simulator node delivers it (:class:`~sb3_formation.ros.sensing.Deliveries`: the inputs of its observation delay
    before, the reset's while the episode is younger, with their stamps) and flying the engine with their actions, build
    the engine's own delayed rows at every step: every field but two that a robot measures otherwise (the agent
    channel, cast at its teammates' estimated positions; the previous reward, which the engine gives of the true world)."""
    from sb3_formation.ros.onboard import AgentSettings, Onboard, TeamView
    from sb3_formation.ros.scans import Scan
    from sb3_formation.ros.sensing import Deliveries, published_team

    policy = OnnxPolicy(MODEL, threads=1)
    env, rows = realistic_env(policy.config, seed=1)
    engine, config = env.engine, env.config
    onboards = [Onboard(policy, AgentSettings(agent=i, filter_disturbances="realistic")) for i in range(config.n_agents)]
    layout = env.observation_layout
    skipped = {"lidar_agents", "previous_reward"}
    delays = engine.disturber.observation_delays[rows].copy()
    assert {0, 1} <= set(delays.tolist()), f"the seed must draw both delays of realistic, got {delays}"
    deliveries: Deliveries = Deliveries()
    deliveries.start(delays)
    observations = np.stack([engine.latest.observations[row] for row in range(rows.start, rows.stop)])
    increment = 2.0 * math.pi / config.lidar_rays
    reach = (config.agent_radius, config.agent_radius + config.lidar_range)
    for step in range(40):
        deliveries.add((step, published_team(engine, env.team, stopped_by_agents=False)))
        actions = np.empty((config.n_agents, 2))
        for agent, onboard in enumerate(onboards):
            stamp, team = deliveries.delivered(agent)
            assert stamp == max(step - int(delays[agent]), 0)
            scan = Scan(team.ranges[agent], float(team.scan_angles[agent]), increment, *reach)
            view = TeamView(team.positions, team.velocities, team.headings)
            done = onboard.step(scan, view, float(team.forward_speeds[agent]), env.goal, stamp=stamp)
            for name, part in layout.items():
                if name not in skipped:
                    np.testing.assert_allclose(
                        done.row[part], observations[agent, part], rtol=2**-23, atol=1e-6, err_msg=f"{name}, {agent}, {step}"
                    )
            actions[agent] = done.action
        observations, _, terminated, truncated, _ = env.step_array(actions)
        assert not (terminated or truncated)


def test_the_two_commands_fly_a_team_one_process_per_agent(tmp_path) -> None:
    """``sb3-formation ros sim`` and ``sb3-formation ros agents --process-per-agent``, as a user starts them: the
    episode flown is the evaluation's (scans that see through the agents: positions within 1e-6 m), and the agents'
    processes end cleanly when stopped."""
    worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0)
    domain = str(100 + WORKER_DOMAINS * worker + WORKER_DOMAINS - 1)
    command = [sys.executable, "-m", "sb3_formation.cli", "ros"]
    out = tmp_path / "episodes.npz"
    lockstep = ["--ros-args", "-p", f"input_timeout:={LOCKSTEP_TIMEOUT}"]
    agents = subprocess.Popen(
        [*command, "agents", "pretrained:ch5-bearing", "--process-per-agent", "--domain-id", domain, *lockstep],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    try:
        sim = [*command, "sim", "pretrained:ch5-bearing", "--see-through-agents", "--out", str(out), "--domain-id", domain]
        sim += ["--command-timeout", "120"]  # the agents' first step compiles the lidar's kernels on a cold cache
        done = subprocess.run(sim, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr[-2000:]
        assert "seed 0: success in" in done.stdout, done.stdout
    finally:
        log = stopped(agents, signal.SIGTERM)  # as a process manager stops it: the parent stops its children
    assert agents.returncode == 0, log[-2000:]
    assert "Traceback" not in log, log[-2000:]
    reference = evaluated(MODEL, 1)
    with np.load(out) as flown:
        assert bool(flown["success"][0]) and int(flown["steps"][0]) == reference.episodes[0]["length"]
        common = int(flown["steps"][0]) + 1
        difference = np.linalg.norm(flown["positions_0"] - reference.trajectories.positions[0, :common], axis=-1).max()
    assert difference <= 1e-6


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"watchdog_rate": 0.0}, "watchdog_rate must be a number > 0"),
        ({"input_timeout": -1.0}, "input_timeout must be a number > 0"),
        ({"agent": -1}, "agent must be an integer >= 0"),
        ({"stage": 4}, "stage must be 1, 2 or 3"),
        ({"odom_topic": "/odom"}, "odom_topic must hold {index}"),
        ({"neighbour_message_topic": "/message"}, "neighbour_message_topic must hold {index}"),
        ({"filter_disturbances": "gentle"}, "filter_disturbances: disturbances 'gentle' are neither a profile"),
    ],
)
def test_bad_agent_settings_are_refused_in_one_line(change: dict, message: str) -> None:
    with pytest.raises(ValueError, match=re.escape(message)):
        AgentSettings(**change)


def test_a_bad_parameter_override_is_refused(context, policy) -> None:
    """``--ros-args -p watchdog_rate:=0.0`` reaches the same check as the settings."""
    from rclpy.parameter import Parameter

    with pytest.raises(ValueError, match="watchdog_rate must be a number > 0"):
        AgentNode(policy, AgentSettings(), context=context, parameter_overrides=[Parameter("watchdog_rate", value=0.0)])


def test_free_running_steps_at_the_clock_and_agents_follow_sim_time(context) -> None:
    """Free-running: the simulator steps with the latest commands at ``rate`` times real time, never faster; agents in
    free mode on the simulator's clock (``use_sim_time``) act on every scan and bring the team towards its goal."""
    from rclpy.parameter import Parameter

    from sb3_formation.ros.sim_node import SimNode, SimSettings

    policy = OnnxPolicy(MODEL, threads=1)
    config = policy.config.replace(stage=3)
    sim = SimNode(config, SimSettings(synchronous=False, rate=4.0), context=context)
    on_sim_time = [Parameter("use_sim_time", value=True)]
    agents = [
        AgentNode(policy, AgentSettings(agent=i), namespace=f"agent_{i}", context=context, parameter_overrides=on_sim_time)
        for i in range(config.n_agents)
    ]
    executor = SingleThreadedExecutor(context=context)
    for node in [sim, *agents]:
        executor.add_node(node)
    engine, rows = sim.env.engine, sim.env.engine.team_rows(sim.env.team)
    goal = engine.episodes.goals[sim.env.team].copy()
    start_distance = float(np.linalg.norm(engine.latest.positions[rows].mean(axis=0) - goal))
    started = time.monotonic()
    spin_until(executor, lambda: time.monotonic() - started > 4.0, timeout=60.0)
    wall, steps = time.monotonic() - started, sim.env.step_count
    executor.shutdown()
    assert 0 < steps * config.dt <= 4.0 * wall * 1.05, (steps, wall)  # at most the rate (a loaded machine: fewer)
    distance = float(np.linalg.norm(engine.latest.positions[rows].mean(axis=0) - goal))
    assert distance < start_distance - 0.5 * steps * config.dt * config.v_max, (start_distance, distance, steps)


def test_the_nodes_import_no_learning_stack() -> None:
    """Measured in a fresh interpreter of the ROS environment (where torch is installed): the nodes and their command
    load neither torch nor Stable-Baselines3."""
    code = (
        "import sys, sb3_formation.ros.agent_node, sb3_formation.ros.sim_node, sb3_formation.ros.launch; "
        "print(sorted(m for m in ('torch', 'stable_baselines3', 'matplotlib') if m in sys.modules))"
    )
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == "[]"


def test_ctrl_c_stops_a_team_of_processes_even_where_it_was_ignored(context) -> None:
    """``--process-per-agent`` started with SIGINT ignored (``nohup``, a background job): the agents come up (their
    command topics have publishers), and Ctrl-C then stops the parent and, through it, every agent's process."""
    domain = os.environ["ROS_DOMAIN_ID"]  # the context's own
    command = [sys.executable, "-m", "sb3_formation.ros", "agents", str(MODEL), "--agents", "0,1", "--process-per-agent"]
    team = subprocess.Popen(
        [*command, "--domain-id", domain],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
        start_new_session=True,
    )
    listener = Node("listener", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(listener)
    try:
        topics = ("/agent_0/cmd_vel", "/agent_1/cmd_vel")
        spin_until(executor, lambda: all(listener.count_publishers(topic) for topic in topics), timeout=120.0)
    finally:
        log = stopped(team, signal.SIGINT)
        executor.shutdown()
    assert team.returncode == 0, log[-2000:]
    assert "Traceback" not in log, log[-2000:]


def test_a_second_process_flying_the_same_agent_stops_the_simulator(context, policy) -> None:
    """Two agent nodes of the same index in one domain (a process left running, a robot started twice): the
    synchronous simulator refuses to fly on in one line rather than step with both's commands."""
    from sb3_formation.ros.sim_node import SimNode, SimSettings

    sim = SimNode(policy.config.replace(stage=3), SimSettings(), context=context)
    twins = [
        AgentNode(policy, AgentSettings(agent=0, synchronous=True), name=f"twin_{k}", namespace="agent_0", context=context)
        for k in range(2)
    ]
    executor = SingleThreadedExecutor(context=context)
    for node in [sim, *twins]:
        executor.add_node(node)
    with pytest.raises(RuntimeError, match="several publishers on /agent_0/cmd_vel"):
        spin_until(executor, lambda: False, timeout=30.0)
    executor.shutdown()


# Reliability on the robot: every input checked, zero commands, the node alive (docs/guarantees.md, "On the robot") ----


#: ``/rosout`` as its publishers offer it (transient local): a line logged before the subscription matched still comes.
ROSOUT_QOS = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


class Driven:
    """Agent 0's node driven in process through its own subscriptions' and watchdog timer's callbacks (rclpy's objects,
    as the executor calls them: the order of its inputs is the test's), its commands and its log lines received over
    real topics by a listener on an executor of its own (the node's timer never fires by itself)."""

    def __init__(self, context: rclpy.context.Context, policy: OnnxPolicy, **settings: Any) -> None:
        from rcl_interfaces.msg import Log

        settings = {"failed_after": 0.0, **settings}  # the one node of the team: its teammates do not fail unless asked
        self.node = AgentNode(policy, AgentSettings(agent=0, **settings), namespace="agent_0", context=context)
        self.callbacks = {subscription.topic_name: subscription.callback for subscription in self.node.subscriptions}
        (self.watchdog,) = [timer.callback for timer in self.node.timers]
        self.n_agents = policy.config.n_agents
        self.listener = Node("driven_listener", context=context)
        self.commands: list[Twist] = []
        self.lines: list[str] = []
        everything = QoSProfile(depth=100_000)
        self.listener.create_subscription(Twist, "/agent_0/cmd_vel", self.commands.append, everything)
        logger = self.node.get_logger().name
        self.listener.create_subscription(
            Log, "/rosout", lambda line: self.lines.append(line.msg) if line.name == logger else None, ROSOUT_QOS
        )
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.listener)
        self.expected = 0  # commands the node has published so far
        spin_until(self.executor, lambda: self.node.commands.get_subscription_count() > 0)

    def now(self) -> float:
        return self.node.get_clock().now().nanoseconds / 1e9

    def odometry(self, index: int, position, seconds: float | None = None, velocity=(0.0, 0.0), yaw: float = 0.0):
        stamp = stamp_of(self.now() if seconds is None else seconds)
        return odometry_message(
            stamp, ("map", f"agent_{index}/base_link"), np.asarray(position), yaw, np.asarray(velocity), 0.0
        )

    def scan(self, seconds: float | None = None, ranges: np.ndarray | None = None) -> LaserScan:
        rays = 90
        message = hand_scan(np.full(rays, np.inf) if ranges is None else ranges, 0.0, 2 * math.pi / rays)
        message.header.stamp = stamp_of(self.now() if seconds is None else seconds)
        return message

    def send(self, topic: str, message: Any) -> None:
        self.callbacks[topic](message)

    def team(self, positions: np.ndarray = TEAM) -> None:
        for index in range(self.n_agents):
            self.send(f"/agent_{index}/odom", self.odometry(index, positions[index]))

    def command(self, scan: LaserScan | None = None) -> Twist:
        """The command the node publishes for a scan (a fresh empty one by default)."""
        self.send("/agent_0/scan", self.scan() if scan is None else scan)
        return self.next_command()

    def next_command(self) -> Twist:
        self.expected += 1
        spin_until(self.executor, lambda: len(self.commands) >= self.expected)
        return self.commands[self.expected - 1]


def values(command: Twist) -> list[float]:
    return [command.linear.x, command.linear.y, command.linear.z, command.angular.x, command.angular.y, command.angular.z]


def is_zero(command: Twist) -> bool:
    return all(value == 0.0 for value in values(command))


def is_moving(command: Twist) -> bool:
    return all(math.isfinite(value) for value in values(command)) and abs(command.linear.x) + abs(command.linear.y) > 0


GOAL = np.array([12.0, 5.0])


def turned_away(message: Odometry) -> Odometry:
    """``message`` with an orientation that is no rotation (a quaternion of norm 2)."""
    message.pose.pose.orientation.x, message.pose.pose.orientation.w = 2.0, 0.0
    return message


@pytest.mark.parametrize("safety_filter", [True, False], ids=["filter", "no-filter"])
def test_nan_or_huge_poses_velocities_and_goals_give_zero_commands_and_the_node_lives(context, policy, safety_filter) -> None:
    """A teammate's NaN position, the robot's own NaN velocity, a finite position of 1e9, an orientation that is not a
    rotation, and a NaN goal (latched: it comes again on a restart): each gives a zero command and a warning naming
    it, with the filter on and off, and the node acts again once the input is usable."""
    driven = Driven(context, policy, safety_filter=safety_filter)
    driven.send("/goal", goal_message(stamp_of(0.0), "map", GOAL))
    driven.team()
    assert is_moving(driven.command())
    broken = {
        "agent 1's position": lambda: driven.send("/agent_1/odom", driven.odometry(1, [math.nan, 1.0])),
        "agent 0's velocity": lambda: driven.send("/agent_0/odom", driven.odometry(0, TEAM[0], velocity=(math.nan, 0.0))),
        "agent 2's huge position": lambda: driven.send("/agent_2/odom", driven.odometry(2, [1e9, 1.0])),
        "agent 3's orientation": lambda: driven.send("/agent_3/odom", turned_away(driven.odometry(3, TEAM[3]))),
    }
    for what, breaking in broken.items():
        breaking()
        assert is_zero(driven.command()), what
        driven.team()
        assert is_moving(driven.command()), f"{what} usable again: the agent must move"
    driven.send("/goal", goal_message(stamp_of(1.0), "map", np.array([math.nan, 5.0])))
    assert is_zero(driven.command()), "a NaN goal"
    driven.send("/goal", goal_message(stamp_of(2.0), "map", GOAL))
    assert is_moving(driven.command())
    spin_until(driven.executor, lambda: bool(driven.lines))  # one a second: the first
    assert "odometry of agent 1: agent 1's position [nan, 1.0] is not a finite point" in driven.lines[0], driven.lines
    assert all("\n" not in line for line in driven.lines)
    driven.executor.shutdown()


def test_inputs_stamped_in_the_future_are_unusable(context, policy) -> None:
    """A teammate's odometry and the scan stamped one hour ahead of the node's clock give zero commands at once, from
    the scan and from the watchdog (before, they never grew stale and the last command stood); a stamp within
    ``future_tolerance`` ahead is taken."""
    driven = Driven(context, policy)
    driven.send("/goal", goal_message(stamp_of(0.0), "map", GOAL))
    driven.team()
    assert is_moving(driven.command(driven.scan(driven.now() + 0.2)))  # within future_tolerance (0.5 s)
    driven.send("/agent_3/odom", driven.odometry(3, TEAM[3], driven.now() + 3600.0))
    assert is_zero(driven.command(driven.scan(driven.now() + 3600.0)))
    driven.watchdog()
    assert is_zero(driven.next_command()), "the watchdog must stop the robot too"
    spin_until(driven.executor, lambda: bool(driven.lines))
    assert "ahead of the clock (future_tolerance 0.5 s)" in driven.lines[0], driven.lines
    driven.team()
    assert is_moving(driven.command())
    driven.executor.shutdown()


def test_a_scan_of_a_million_ranges_is_refused_before_any_work(context, policy) -> None:
    """A ``LaserScan`` of 10^6 ranges (once a MemoryError that ended the node) or 10^5 (1.9 s of work per scan) is
    refused in one line, at once (a generous bound: nothing is resampled), with a zero command."""
    from sb3_formation.ros.onboard import MAX_SCAN_RANGES

    driven = Driven(context, policy)
    driven.send("/goal", goal_message(stamp_of(0.0), "map", GOAL))
    driven.team()
    for count in (10**6, 10**5, MAX_SCAN_RANGES + 1):
        scan = driven.scan(ranges=np.full(count, 3.0))
        started = time.monotonic()
        driven.send("/agent_0/scan", scan)
        assert time.monotonic() - started < 0.5, count
        assert is_zero(driven.next_command()), count
    spin_until(driven.executor, lambda: bool(driven.lines))
    assert driven.lines[0] == f"agent 0 stopped: a scan of 1000000 ranges (1 to {MAX_SCAN_RANGES} are taken)"
    assert is_moving(driven.command(driven.scan(ranges=np.full(MAX_SCAN_RANGES, 3.0))))
    driven.executor.shutdown()


def test_parameters_of_another_type_are_one_line_errors(context, policy) -> None:
    """``-p input_timeout:=2`` (an integer for a number) is taken as 2.0; ``-p agent:=1.5`` and
    ``-p input_timeout:=abc`` are one-line ``ValueError`` s naming the parameter (once rclpy's
    InvalidParameterTypeException), for the agent node and the simulator node alike; and so from the command line."""
    from rclpy.parameter import Parameter

    from sb3_formation.ros.sim_node import SimNode

    node = AgentNode(policy, AgentSettings(), context=context, parameter_overrides=[Parameter("input_timeout", value=2)])
    assert node.settings.input_timeout == 2.0 and isinstance(node.settings.input_timeout, float)
    node.destroy_node()
    for name, value, message in [
        ("agent", 1.5, "parameter agent must be an integer, got 1.5"),
        ("input_timeout", "abc", "parameter input_timeout must be a number, got 'abc'"),
        ("synchronous", 1, "parameter synchronous must be true or false, got 1"),
    ]:
        with pytest.raises(ValueError, match=re.escape(message)):
            AgentNode(policy, AgentSettings(), context=context, parameter_overrides=[Parameter(name, value=value)])
    sim = SimNode(policy.config, context=context, parameter_overrides=[Parameter("rate", value=2)])
    assert sim.settings.rate == 2.0
    sim.destroy_node()
    with pytest.raises(ValueError, match=re.escape("parameter episodes must be an integer, got 'two'")):
        SimNode(policy.config, context=context, parameter_overrides=[Parameter("episodes", value="two")])
    command = [sys.executable, "-m", "sb3_formation.ros", "agents", str(MODEL), "--agents", "0"]
    done = subprocess.run(
        [*command, "--domain-id", os.environ["ROS_DOMAIN_ID"], "--ros-args", "-p", "agent:=1.5"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2, done.stderr[-2000:]
    assert done.stderr.strip() == "sb3_formation.ros: error: parameter agent must be an integer, got 1.5", done.stderr


def test_disturbances_are_settings_of_both_nodes(context, policy, tmp_path) -> None:
    """The simulator's disturbances and the agents' filter bounds are settings and ROS parameters: a profile's name or
    a file gives them (the simulator's engine draws them, the agent's filter declares its bounds from them), the
    defaults are the ideal world's, and a name that is neither is a one-line error before anything starts, also from
    the command line."""
    from rclpy.parameter import Parameter

    from sb3_formation.env.disturbances import load_disturbances
    from sb3_formation.ros.sim_node import SimNode, SimSettings
    from sb3_formation.safety.filter import FilterBounds

    file = tmp_path / "mine.yaml"
    file.write_text("profile: realistic\ntiming:\n  observation_delay: [2, 2]\n")
    sim = SimNode(policy.config, SimSettings(disturbances=str(file)), context=context)
    assert sim.env.engine.disturber is not None and sim.config.disturbances == load_disturbances(file)
    sim.destroy_node()
    sim = SimNode(policy.config, context=context, parameter_overrides=[Parameter("disturbances", value="harsh")])
    assert sim.settings.disturbances == "harsh" and sim.config.disturbances == load_disturbances("harsh")
    sim.destroy_node()
    assert SimNode(policy.config, context=context).env.engine.disturber is None
    with pytest.raises(ValueError, match=re.escape("disturbances: disturbances 'gentle' are neither a profile")):
        SimNode(policy.config, context=context, parameter_overrides=[Parameter("disturbances", value="gentle")])
    node = AgentNode(policy, AgentSettings(filter_disturbances="realistic"), name="bounded", context=context)
    assert node.onboard.policy.filter.bounds == FilterBounds.declared(load_disturbances("realistic"))
    assert AgentNode(policy, AgentSettings(), name="exact", context=context).onboard.policy.filter.bounds.is_exact
    for command, option in (("sim", "--disturbances"), ("agents", "--filter-disturbances")):
        done = subprocess.run(
            [sys.executable, "-m", "sb3_formation.ros", command, str(MODEL), option, "gentle"],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert done.returncode == 2, done.stderr[-2000:]
        assert done.stderr.strip().startswith(f"sb3_formation.ros: error: {option}: disturbances 'gentle' are neither")
        assert "\n" not in done.stderr.strip()


#: The fuzz test's corrupted inputs.
FUZZ_INPUTS = 10_000


def test_ten_thousand_corrupted_inputs_give_finite_commands_zero_whenever_unusable(context, policy) -> None:
    """A seeded stream of the team's odometry, the goal and the scan, 15 % of them corrupted (NaN, inf,
    huge values, orientations that are no rotation, scans of no, many or a million ranges or of NaN angles or limits,
    other frames, stamps far ahead or behind the clock, inputs missing), drives agent 0's node (filter on) through
    its callbacks: after every scan and many watchdog ticks, each command it publishes is finite, and zero whenever
    the newest input of any kind is unusable (a rule of the test's own: docs/guarantees.md); it never raises, and
    acts again on usable inputs at the end."""
    from sb3_formation.ros.onboard import MAX_SCAN_RANGES

    driven = Driven(context, policy, input_timeout=5.0)  # stale inputs are 10 s old or more: no test stall counts
    n_agents, rng = driven.n_agents, np.random.default_rng(2024)
    bad_number = [math.nan, math.inf, -math.inf, 1e9, -1e300]
    latest: dict[str, bool] = {}  # input -> usable (absent: never sent)
    corrupted = scans = ticks = 0
    zero_expected: list[bool] = []  # per command: the inputs were unusable

    def stamp(usable: bool, judge_age: bool = True) -> tuple[float, bool]:
        """A stamp near now, or (when not ``usable``) far ahead or, for inputs whose age counts, far behind."""
        if usable:
            return driven.now() - rng.uniform(0.0, 0.05) + (0.3 if rng.random() < 0.1 else 0.0), True
        if not judge_age or rng.random() < 0.5:
            return driven.now() + rng.uniform(10.0, 3600.0), False
        return driven.now() - rng.uniform(10.0, 3600.0), False

    def odometry(index: int, corrupt: bool) -> tuple[Odometry, bool]:
        kind = rng.integers(5) if corrupt else -1
        seconds, usable = stamp(kind != 0)
        velocity = rng.uniform(-0.05, 0.05, 2)
        position = TEAM[index] + rng.uniform(-0.5, 0.5, 2)
        if kind == 1:
            position[rng.integers(2)] = rng.choice(bad_number)
        elif kind == 2:
            velocity[rng.integers(2)] = rng.choice(bad_number)
        message = driven.odometry(index, position, seconds, velocity, yaw=float(rng.uniform(-3, 3)))
        if kind == 3:
            turned_away(message)
        elif kind == 4:
            message.header.frame_id = "odom"
        return message, kind in (-1, 0) and usable

    def scan(corrupt: bool) -> tuple[LaserScan, bool]:
        kind = rng.integers(7) if corrupt else -1
        seconds, usable = stamp(kind != 0)
        count = {1: 0, 2: int(rng.integers(MAX_SCAN_RANGES + 1, 4 * MAX_SCAN_RANGES))}.get(kind, int(rng.integers(3, 400)))
        if kind == 2 and rng.random() < 0.002:
            count = 10**6
        ranges = rng.uniform(0.1, 5.0, count)
        if count and rng.random() < 0.3:  # returns that are no returns (REP 117): usable
            ranges[rng.integers(count, size=count // 3 + 1)] = rng.choice([math.nan, math.inf, -1.0, 1e30])
        message = hand_scan(ranges, float(rng.uniform(-math.pi, math.pi)), 2 * math.pi / max(count, 1))
        message.header.stamp = stamp_of(seconds)
        if kind == 3:
            message.angle_min = float(rng.choice([math.nan, math.inf]))
        elif kind == 4:
            message.angle_increment = float(rng.choice([math.nan, -math.inf]))
        elif kind == 5:
            message.range_min, message.range_max = float(rng.choice([math.nan, 40.0])), 30.0
        elif kind == 6:
            message.range_max = math.nan
        return message, kind == -1 and usable

    def goal(corrupt: bool) -> tuple[PointStamped, bool]:
        kind = rng.integers(3) if corrupt else -1
        seconds, usable = stamp(kind != 0, judge_age=False)
        point = GOAL + rng.uniform(-1.0, 1.0, 2)
        if kind == 1:
            point[rng.integers(2)] = rng.choice(bad_number)
        message = goal_message(stamp_of(max(seconds, 0.0)), "map", point)
        if kind == 2:
            message.header.frame_id = "odom"
        return message, kind == -1 and usable

    def unusable() -> bool:
        names = ["scan", "goal", *(f"odometry {index}" for index in range(n_agents))]
        return not all(latest.get(name, False) for name in names)

    started = time.monotonic()
    while corrupted < FUZZ_INPUTS:
        for index in range(n_agents):
            if rng.random() < 0.9:
                corrupt = bool(rng.random() < 0.15)
                message, latest[f"odometry {index}"] = odometry(index, corrupt)
                corrupted += corrupt
                driven.send(f"/agent_{index}/odom", message)
        if rng.random() < 0.05 or "goal" not in latest:
            corrupt = bool(rng.random() < 0.15)
            message, latest["goal"] = goal(corrupt)
            corrupted += corrupt
            driven.send("/goal", message)
        corrupt = bool(rng.random() < 0.15)
        message, latest["scan"] = scan(corrupt)
        corrupted += corrupt
        scans += 1
        zero_expected.append(unusable())
        command = driven.command(message)
        assert all(math.isfinite(value) for value in values(command)), (scans, command)
        assert is_zero(command) or not zero_expected[-1], f"scan {scans}: a command on unusable inputs: {command}"
        if rng.random() < 0.2:  # a watchdog tick: a zero command exactly when an input is unusable
            ticks += 1
            driven.watchdog()
            if unusable():
                assert is_zero(driven.next_command()), f"the watchdog after scan {scans}"
    driven.team()
    driven.send("/goal", goal_message(stamp_of(0.0), "map", GOAL))
    last = driven.command()
    assert is_moving(last), "usable inputs again: the agent must act"
    spin_until(driven.executor, lambda: len(driven.commands) >= driven.expected)
    elapsed = time.monotonic() - started
    assert len(driven.commands) == driven.expected, "a command that was not expected (the watchdog on usable inputs?)"
    acted = sum(not expected for expected in zero_expected)
    print(f"{corrupted} corrupted inputs, {scans} scans ({acted} on usable inputs), {ticks} watchdog ticks, {elapsed:.1f} s")
    assert acted > 0.1 * scans, "the stream must leave the node usable inputs often enough to act"
    driven.executor.shutdown()


@pytest.mark.parametrize("mode", ["sync", "free"])
def test_a_simulator_that_stops_gives_zero_commands(context, policy, mode) -> None:
    """The simulator stops mid-episode (its node spun no more: it publishes nothing, as a killed process): synchronous
    agents (which once published nothing more) and free-running agents on its ``/clock`` (whose watchdog once never
    fired, the clock having stopped) publish zero commands, within ``input_timeout`` of the wall clock."""
    from rclpy.parameter import Parameter

    from sb3_formation.ros.sim_node import SimNode, SimSettings

    synchronous = mode == "sync"
    config = policy.config.replace(stage=3)
    sim = SimNode(config, SimSettings(synchronous=synchronous, rate=4.0, command_timeout=120.0), context=context)
    on_sim_time = [Parameter("use_sim_time", value=not synchronous)]
    agents = [
        AgentNode(
            policy,
            AgentSettings(agent=i, synchronous=synchronous),
            namespace=f"agent_{i}",
            context=context,
            parameter_overrides=on_sim_time,
        )
        for i in range(config.n_agents)
    ]
    listener = Node("listener", context=context)
    commands: list[Twist] = []
    listener.create_subscription(Twist, "/agent_0/cmd_vel", commands.append, 1000)
    executor = SingleThreadedExecutor(context=context)
    for node in [sim, *agents, listener]:
        executor.add_node(node)
    spin_until(executor, lambda: sim.env.step_count >= 10 and any(is_moving(command) for command in commands), 120.0)
    executor.remove_node(sim)
    stopped_at, seen = time.monotonic(), len(commands)
    spin_until(executor, lambda: any(is_zero(command) for command in commands[seen:]), timeout=30.0)
    waited = time.monotonic() - stopped_at
    spin_until(executor, lambda: len(commands) >= seen + 5, timeout=30.0)  # and zero from then on
    first_zero = next(k for k, command in enumerate(commands) if k >= seen and is_zero(command))
    assert all(is_zero(command) for command in commands[first_zero:])
    executor.shutdown()
    assert waited < 10.0, waited  # input_timeout (1 s) plus a generous allowance for a loaded machine


def test_a_second_node_flying_the_same_agent_is_noticed_in_free_mode(context, policy) -> None:
    """Two free-running agent nodes of the same index (a process left running, a robot started twice): the free
    simulator stops in one line, as the synchronous one does, and without a simulator each node stops the robot
    (zero commands) and says why."""
    from rcl_interfaces.msg import Log

    from sb3_formation.ros.sim_node import SimNode, SimSettings

    twins = [
        AgentNode(policy, AgentSettings(agent=0), name=f"twin_{k}", namespace="agent_0", context=context) for k in range(2)
    ]
    listener = Node("listener", context=context)
    commands: list[Twist] = []
    lines: list[str] = []
    listener.create_subscription(Twist, "/agent_0/cmd_vel", commands.append, 1000)
    listener.create_subscription(Log, "/rosout", lambda line: lines.append(line.msg), ROSOUT_QOS)
    executor = SingleThreadedExecutor(context=context)
    for node in [*twins, listener]:
        executor.add_node(node)
    spin_until(executor, lambda: any("another node publishes on /agent_0/cmd_vel" in line for line in lines))
    spin_until(executor, lambda: len(commands) >= 4)
    assert all(is_zero(command) for command in commands)
    sim = SimNode(policy.config.replace(stage=3), SimSettings(synchronous=False), context=context)
    executor.add_node(sim)
    with pytest.raises(RuntimeError, match="several publishers on /agent_0/cmd_vel"):
        spin_until(executor, lambda: False, timeout=30.0)
    executor.shutdown()


def test_a_command_that_is_not_finite_is_a_zero_command_for_the_simulator(context, policy) -> None:
    """A ``Twist`` with ``linear.x = inf`` (once the end of the free-running simulator): the simulator warns, takes it
    as a zero command and steps on."""
    from rcl_interfaces.msg import Log

    from sb3_formation.ros.sim_node import SimNode, SimSettings

    sim = SimNode(policy.config.replace(stage=3), SimSettings(synchronous=False, rate=10.0), context=context)
    pilot = Node("pilot", context=context)
    publisher = pilot.create_publisher(Twist, "/agent_0/cmd_vel", 10)
    lines: list[str] = []
    pilot.create_subscription(Log, "/rosout", lambda line: lines.append(line.msg), ROSOUT_QOS)
    executor = SingleThreadedExecutor(context=context)
    for node in [sim, pilot]:
        executor.add_node(node)
    spin_until(executor, lambda: publisher.get_subscription_count() > 0)
    bad = Twist()
    bad.linear.x = math.inf
    publisher.publish(bad)
    spin_until(executor, lambda: any("is not finite: taken as a zero command" in line for line in lines))
    steps = sim.env.step_count
    spin_until(executor, lambda: sim.env.step_count >= steps + 5)
    executor.shutdown()


def test_the_agents_processes_die_with_a_killed_parent(context) -> None:
    """``--process-per-agent`` whose parent is killed with SIGKILL (it cannot pass anything on): its agents' processes
    end too (PR_SET_PDEATHSIG), where they once flew on; their command topics lose their publishers."""
    domain = os.environ["ROS_DOMAIN_ID"]  # the context's own
    command = [sys.executable, "-m", "sb3_formation.ros", "agents", str(MODEL), "--agents", "0,1", "--process-per-agent"]
    team = subprocess.Popen(
        [*command, "--domain-id", domain],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    listener = Node("listener", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(listener)
    topics = ("/agent_0/cmd_vel", "/agent_1/cmd_vel")
    try:
        spin_until(executor, lambda: all(listener.count_publishers(topic) for topic in topics), timeout=120.0)
        team.kill()
        team.communicate(timeout=60)
        spin_until(executor, lambda: not any(listener.count_publishers(topic) for topic in topics), timeout=60.0)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(team.pid, signal.SIGKILL)  # whatever is left of the group
        executor.shutdown()


def test_a_simulator_that_fails_keeps_the_episodes_it_played(context, tmp_path) -> None:
    """``ros sim --out`` that stops on its command timeout after one of three episodes (its agents gone): it says so
    in one line (exit 2) and the episode it played is in ``--out`` (written as each episode ends)."""
    from test_messages import untrained

    from sb3_formation.env.config import FormationConfig
    from sb3_formation.sb3.onnx_export import export_onnx

    model = export_onnx(untrained(FormationConfig.task("ch5-bearing", stage=3, max_steps=20), True, 3), tmp_path / "m.onnx")
    out = tmp_path / "episodes.npz"
    options = ["--episodes", "3", "--out", str(out), "--command-timeout", "3", "--domain-id", os.environ["ROS_DOMAIN_ID"]]
    sim = subprocess.Popen(
        [sys.executable, "-m", "sb3_formation.ros", "sim", str(model), *options],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    policy = OnnxPolicy(model, threads=1)
    agents = [
        AgentNode(policy, AgentSettings(agent=i, synchronous=True), namespace=f"agent_{i}", context=context)
        for i in range(policy.config.n_agents)
    ]
    executor = SingleThreadedExecutor(context=context)
    for node in agents:
        executor.add_node(node)
    try:
        spin_until(executor, lambda: out.exists(), timeout=300.0)  # the first episode is written as it ends
        for node in agents:  # the agents go
            executor.remove_node(node)
            node.destroy_node()
        stdout, stderr = sim.communicate(timeout=120)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(sim.pid, signal.SIGKILL)
        executor.shutdown()
    assert sim.returncode == 2, stderr[-2000:]
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("sb3_formation.ros: error: no command from agents"), stderr[-2000:]
    assert "seed 0: failure in 20 steps" in stdout, stdout
    with np.load(out) as flown:
        assert flown["seed"].tolist()[0] == 0 and int(flown["steps"][0]) == 20
        assert flown["positions_0"].shape == (21, policy.config.n_agents, 2)
