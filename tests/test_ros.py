"""The ROS 2 nodes over real rclpy publishers and subscribers (``docs/deployment.md``): ``make test-ros`` runs these in
the ROS environment (``.venv-ros``); elsewhere they are skipped.

Every test process keeps discovery on this machine and takes a ROS domain of its own (one per pytest-xdist worker).
"""

from __future__ import annotations

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


DOMAINS = iter(range(20))


@pytest.fixture
def context() -> Iterator[rclpy.context.Context]:
    """A fresh rclpy context per test, in a domain of its own (no latched goal of another test reaches it)."""
    worker = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0)
    os.environ["ROS_DOMAIN_ID"] = str(100 + 20 * worker + next(DOMAINS))
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
        settings = AgentSettings(agent=0, input_timeout=1.0, watchdog_rate=20.0)
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


def fly(
    context: rclpy.context.Context,
    model: Path,
    episodes: int,
    see_through: bool,
    observe: bool = False,
    extra_nodes: list[Node] | None = None,
    heard: Callable[[int], bool] | None = None,
) -> tuple:
    """The simulator node and a team's agent nodes (and ``extra_nodes``) in one executor, synchronous, filter on: the
    simulator's episode records, the env's observation rows of every step, and each agent's published observations
    (with ``observe``). After the last step it spins until ``heard(steps)`` holds too (what ``extra_nodes`` listen to
    may still be on its way)."""
    from sb3_formation.ros.sim_node import SimNode, SimSettings

    policy = OnnxPolicy(model, threads=1)
    config = policy.config.replace(stage=3)
    settings = SimSettings(seed=0, episodes=episodes, see_through_agents=see_through, command_timeout=120.0)
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
            AgentSettings(agent=index, synchronous=True, observation_topic="observation" if observe else ""),
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


def evaluated(model: Path, episodes: int):
    """The same episodes evaluated in process (``sb3-formation evaluate safe:onnx:<model>``'s loop)."""
    from sb3_formation.experiment.evaluation import evaluate

    return evaluate(SafePolicy(OnnxPolicy(model, threads=1)), episodes, stage=3, seed=0, n_envs=episodes, record=episodes)


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

        def predict(self, observation, state=None, episode_start=None, deterministic=True):
            if state is not None:
                state = (state[0], np.zeros_like(state[1]))
            return self.policy.predict(observation, state, episode_start, deterministic)

    deaf = evaluate(SafePolicy(Deaf(OnnxPolicy(model, threads=1))), 1, stage=3, seed=0, n_envs=1, record=1)
    assert largest_difference(results[0], deaf.trajectories, 0) > 1e-3


def test_the_two_commands_fly_a_team_one_process_per_agent(tmp_path) -> None:
    """``sb3-formation ros sim`` and ``sb3-formation ros agents --process-per-agent``, as a user starts them: the
    episode flown is the evaluation's (scans that see through the agents: positions within 1e-6 m), and the agents'
    processes end cleanly when stopped."""
    domain = str(100 + 20 * int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw") or 0) + 19)
    command = [sys.executable, "-m", "sb3_formation.cli", "ros"]
    out = tmp_path / "episodes.npz"
    agents = subprocess.Popen(
        [*command, "agents", "pretrained:ch5-bearing", "--process-per-agent", "--domain-id", domain],
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
