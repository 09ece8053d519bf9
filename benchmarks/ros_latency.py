"""Scan-to-command time of one agent node over ROS 2, filter on, against the same work in process.

The target: one agent's scan-to-command time at most 5 ms (median) and 20 ms (99th percentile) on one core, with the
safety filter on. One agent node (agent 0 of the shipped ``ch5-bearing`` policy, free mode, wall clock, filter on) runs
in a child process started as ``python -m sb3_formation.ros agents MODEL --agents 0 --mode free`` (onnxruntime on one
thread) and pinned to the first core this process may use (``taskset``); this process, the node's publisher and
subscriber, is pinned to the second (both share the one core of a one-core machine).

Inputs: a stage-3 episode of the shipped policy behind the filter, recorded in process (``SafePolicy(OnnxPolicy)`` on
``FormationEnv``), replayed in turn (each pass a new episode: the goal published anew, latched). Per step, every
teammate's ``Odometry`` goes out, then half a period later agent 0's ``LaserScan`` (what a scanner at its centre sees,
:func:`~sb3_formation.ros.scans.merged_scan`), all stamped with the wall-clock time; a step's time runs from just
before the scan is published to the start of the callback that receives the node's ``Twist`` on ``/agent_0/cmd_vel``
(``time.perf_counter`` in this process; its rclpy executor's wake-up counts). Steps are paced at ``--rate`` Hz so that
a command arrives before the next odometry; median, p90, p99 and max over ``--steps`` steps after ``--warm-up`` are
printed.

The reference, measured in the same run on the node's core once it has stopped: the node's work without ROS, the
module the node runs (:meth:`sb3_formation.ros.onboard.Onboard.step`: resample, split, observe, the policy's agent step
behind the filter, remember, command; onnxruntime on one thread), built as the node builds it, for the same steps in
the same order, its median and p99, the ratios ROS / in process, and the largest difference between the node's
commands and the in-process ones (a check that the node did the same work on the same inputs).

Usage (in the ROS environment): ``.venv-ros/bin/python benchmarks/ros_latency.py [--steps 2000] [--rate 20]
[--note "machine shared with other work"] [--out [FILE]]`` (``--out``: also write the output to
``docs/measurements/ros_latency.txt``, or FILE)
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from importlib.metadata import version
from pathlib import Path
from typing import IO, NamedTuple

import numpy as np
import onnxruntime
import rclpy
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PointStamped, Twist
from nav_msgs.msg import Odometry
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.serialization import deserialize_message, serialize_message
from rclpy.utilities import get_rmw_implementation_identifier
from sensor_msgs.msg import LaserScan

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.dynamics import dynamics_model
from sb3_formation.env.formation_env import FormationEnv
from sb3_formation.ros.agent_node import GOAL_QOS
from sb3_formation.ros.messages import goal_message, odometry_message, scan_message, scan_of, stamp_of, twist_command
from sb3_formation.ros.onboard import AgentSettings, Onboard, TeamView
from sb3_formation.ros.scans import merged_scan
from sb3_formation.runtime import load_onnx_policy
from sb3_formation.safety.policy import SafePolicy
from sb3_formation.utils.machine import machine_line

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "src" / "sb3_formation" / "pretrained" / "ch5-bearing" / "final_model.onnx"
OUT = ROOT / "docs" / "measurements" / "ros_latency.txt"
#: The agent whose node runs, and the frames of the simulator node (:class:`~sb3_formation.ros.sim_node.SimSettings`).
AGENT = 0
WORLD_FRAME = "map"
BASE_FRAME = "agent_{index}/base_link"
#: (s) the longest wait for the node: to come up (its imports and numba's compilation), and for one command.
START_TIMEOUT, COMMAND_TIMEOUT = 120.0, 30.0
#: The target (ms): median and 99th percentile of the scan-to-command time.
TARGET_MEDIAN, TARGET_P99 = 5.0, 20.0


class Step(NamedTuple):
    """One recorded step of the team, as the node sees it (holonomic agents: headings 0, body frames the world's)."""

    positions: np.ndarray  #: ``(n, 2)`` (m)
    velocities: np.ndarray  #: ``(n, 2)`` (m/s)
    ranges: np.ndarray  #: ``(n_rays,)`` agent 0's scan (m from its centre, ``inf``: nothing in range)


class Replay(NamedTuple):
    """A recorded episode: its task, goal, steps, and the share of agent 0's actions the filter changed in it."""

    config: FormationConfig
    goal: np.ndarray
    steps: list[Step]
    filter_changed: float


def record_episode(seed: int) -> Replay:
    """A stage-3 episode of the shipped policy behind the safety filter, from ``reset(seed=seed)``."""
    exported = load_onnx_policy(MODEL, threads=1)
    if exported.config.dynamics != "holonomic":
        raise ValueError(f"{MODEL} flies {exported.config.dynamics} agents: this benchmark replays holonomic ones")
    config = exported.config.replace(stage=3)
    env = FormationEnv(config)
    policy = SafePolicy(exported.fit(config))
    observations = np.stack(list(env.reset(seed=seed)[0].values()))
    rows, lidar = env.engine.team_rows(env.team), env.engine.lidars[env.team]
    steps, ended = [], False
    while not ended:
        positions, velocities = env.engine.latest.positions[rows].copy(), env.engine.latest.velocities[rows].copy()
        steps.append(Step(positions, velocities, merged_scan(lidar, positions)[AGENT]))
        actions, _ = policy.predict(observations)
        observations, _, terminated, truncated, _ = env.step_array(actions)
        ended = terminated or truncated
    changed = policy.episode_metrics(slice(AGENT, AGENT + 1))["filter_changed_fraction"]
    return Replay(config, env.goal, steps, changed)


def agent_scan(stamp: Time, ranges: np.ndarray, config: FormationConfig) -> LaserScan:
    """Agent 0's ``LaserScan``: beam k along world angle 2 pi k / n_rays, returns from R_a to R_a + lidar range."""
    reach = (config.agent_radius, config.agent_radius + config.lidar_range)
    return scan_message(stamp, BASE_FRAME.format(index=AGENT), ranges, 0.0, *reach)


def percentiles(seconds: list[float]) -> dict[str, float]:
    """Median, p90, p99 and max of ``seconds``, in ms."""
    values = np.asarray(seconds) * 1e3
    return {
        "median": float(np.median(values)),
        "p90": float(np.percentile(values, 90)),
        "p99": float(np.percentile(values, 99)),
        "max": float(values.max()),
    }


def pin(pid: int, core: int) -> None:
    """Pin every thread of process ``pid`` (threads it starts later inherit the pinning) to ``core``."""
    for task in Path(f"/proc/{pid}/task").iterdir():
        os.sched_setaffinity(int(task.name), {core})


class Feed:
    """The benchmark's node: publishes the team's odometry, the goal and agent 0's scan; times agent 0's commands.

    :param n_agents: the team's size
    """

    def __init__(self, n_agents: int) -> None:
        self.node = Node("ros_latency_feed")
        self.odometry = [self.node.create_publisher(Odometry, f"/agent_{index}/odom", 10) for index in range(n_agents)]
        self.scan = self.node.create_publisher(LaserScan, f"/agent_{AGENT}/scan", 10)
        self.goal = self.node.create_publisher(PointStamped, "/goal", GOAL_QOS)
        self.subscription = self.node.create_subscription(Twist, f"/agent_{AGENT}/cmd_vel", self._on_command, 10)
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self.arrival: float | None = None  # perf_counter() at the last command's callback
        self.command = Twist()

    def _on_command(self, message: Twist) -> None:
        self.arrival, self.command = time.perf_counter(), message

    def connected(self) -> bool:
        """Whether the node is up: subscribed to every input, publishing its commands."""
        publishers = [*self.odometry, self.scan, self.goal]
        return (
            all(publisher.get_subscription_count() for publisher in publishers) and self.subscription.get_publisher_count() > 0
        )

    def spin_until(self, deadline: float) -> None:
        """Handle what arrives until ``deadline`` (``time.perf_counter`` seconds)."""
        while (left := deadline - time.perf_counter()) > 0:
            self.executor.spin_once(timeout_sec=left)

    def command_after(self, message: LaserScan) -> tuple[float, Twist]:
        """Publish ``message`` and wait for the node's command: the seconds from just before publishing to the
        command's callback, and the command.

        :raises TimeoutError: no command within ``COMMAND_TIMEOUT``
        """
        self.arrival = None
        start = time.perf_counter()
        self.scan.publish(message)
        while self.arrival is None:
            if time.perf_counter() - start > COMMAND_TIMEOUT:
                raise TimeoutError(f"no command on /agent_{AGENT}/cmd_vel within {COMMAND_TIMEOUT} s of a scan")
            self.executor.spin_once(timeout_sec=COMMAND_TIMEOUT)
        return self.arrival - start, self.command


def start_node(domain_id: int, core: int, log: IO[bytes]) -> tuple[subprocess.Popen[bytes], list[str]]:
    """The agent node's process (pinned to ``core``) and its command line."""
    taskset = shutil.which("taskset")
    if taskset is None:
        raise FileNotFoundError("taskset (util-linux) is needed to pin the agent node to one core")
    command = [taskset, "-c", str(core), sys.executable, "-m", "sb3_formation.ros", "agents", str(MODEL)]
    command += ["--agents", str(AGENT), "--mode", "free", "--domain-id", str(domain_id)]
    return subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT), command


def stop_node(node: subprocess.Popen[bytes]) -> None:
    """Stop the node's process (SIGTERM: it shuts down cleanly)."""
    if node.poll() is None:
        node.send_signal(signal.SIGTERM)
        try:
            node.wait(timeout=10)
        except subprocess.TimeoutExpired:
            node.kill()
            node.wait()


def wait_for_node(feed: Feed, node: subprocess.Popen[bytes], log: IO[bytes]) -> None:
    """Spin until the node is connected.

    :raises RuntimeError: the node's process ended, or it did not connect within ``START_TIMEOUT``
    """
    deadline = time.perf_counter() + START_TIMEOUT
    while not feed.connected():
        if node.poll() is not None or time.perf_counter() > deadline:
            log.seek(0)
            tail = log.read().decode(errors="replace").strip().splitlines()[-5:]
            state = f"ended with code {node.returncode}" if node.poll() is not None else f"not up in {START_TIMEOUT} s"
            raise RuntimeError(f"the agent node {state}: " + " | ".join(tail))
        feed.spin_until(time.perf_counter() + 0.1)
    feed.spin_until(time.perf_counter() + 0.5)


def over_ros(feed: Feed, replay: Replay, count: int, rate: float) -> tuple[list[float], np.ndarray, list[int]]:
    """Replay ``count`` steps at ``rate`` Hz: each step's scan-to-command seconds, the commands ``(count, 2)``, and the
    steps whose command came after the next step was due."""
    config, period, model = replay.config, 1.0 / rate, dynamics_model(replay.config)
    frames = [(WORLD_FRAME, BASE_FRAME.format(index=index)) for index in range(config.n_agents)]
    seconds, commands, late = [], [], []
    due = time.perf_counter()
    for k in range(count):
        step = replay.steps[k % len(replay.steps)]
        if k % len(replay.steps) == 0:  # a new pass: a new goal, a new episode for the node
            feed.goal.publish(goal_message(stamp_of(time.time()), WORLD_FRAME, replay.goal))
        stamp = stamp_of(time.time())
        for publisher, frame, position, velocity in zip(feed.odometry, frames, step.positions, step.velocities):
            publisher.publish(odometry_message(stamp, frame, position, 0.0, velocity, 0.0))
        feed.spin_until(due + period / 2)
        elapsed, command = feed.command_after(agent_scan(stamp_of(time.time()), step.ranges, config))
        seconds.append(elapsed)
        commands.append(twist_command(command, model, 0.0))
        due += period
        if time.perf_counter() > due:
            late.append(k)
            due = time.perf_counter()
        feed.spin_until(due)
    return seconds, np.array(commands), late


def in_process(replay: Replay, count: int) -> tuple[list[float], np.ndarray, int, int]:
    """The node's work on the same ``count`` steps without ROS: each step's seconds, the commands ``(count, 2)``, the
    steps whose action the filter changed, and those with an obstacle in agent 0's range."""
    onboard = Onboard(load_onnx_policy(MODEL, threads=1), AgentSettings(agent=AGENT))  # as the node builds it
    safe = onboard.policy
    assert isinstance(safe, SafePolicy), "the node's policy is behind the filter"
    headings, obstacles = np.zeros(replay.config.n_agents), onboard.observer.layout["lidar_obstacles"]
    scans = [  # what the node reads: the scan after serialisation (float32 fields)
        scan_of(deserialize_message(serialize_message(agent_scan(stamp_of(0.0), step.ranges, replay.config)), LaserScan))
        for step in replay.steps
    ]
    seconds, commands, changed, near = [], [], 0, 0
    for k in range(count):
        index = k % len(replay.steps)
        if index == 0:
            onboard.reset()
        start = time.perf_counter()
        step = replay.steps[index]
        done = onboard.step(scans[index], TeamView(step.positions, step.velocities, headings), 0.0, replay.goal)
        seconds.append(time.perf_counter() - start)
        commands.append(done.command)
        changed += bool(safe.report is not None and safe.report.changed[0])
        near += bool(done.row[obstacles].min() < 1.0)
    return seconds, np.array(commands), changed, near


def measure_over_ros(
    replay: Replay, count: int, args: argparse.Namespace, cores: tuple[int, int], say: Callable[[str], None]
) -> tuple[list[float], np.ndarray, list[int]]:
    """Start the agent node on ``cores[0]``, replay ``count`` steps to it from this process (on ``cores[1]``) at
    ``args.rate`` Hz (:func:`over_ros`), stop it; ``say`` the node's command line and set-up."""
    node_core, own_core = cores
    with tempfile.TemporaryFile() as log:
        node, command = start_node(args.domain_id, node_core, log)
        shown = " ".join(Path(part).name if part in (sys.executable, command[0]) else part for part in command)
        say(f"  agent node: {shown.replace(str(MODEL), str(MODEL.relative_to(ROOT)))}")
        say(
            f"    on core {node_core}; this process (publisher and subscriber) on core {own_core}; onnxruntime "
            f"{onnxruntime.__version__} on 1 thread; rclpy {version('rclpy')}, {get_rmw_implementation_identifier()}, "
            f"domain {args.domain_id}, discovery localhost"
        )
        try:
            rclpy.init()
            feed = Feed(replay.config.n_agents)
            wait_for_node(feed, node, log)
            seconds, commands, late = over_ros(feed, replay, count, args.rate)
        finally:
            stop_node(node)
            rclpy.try_shutdown()
    return seconds, commands, late


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=2000, help="timed steps (default 2000)")
    parser.add_argument("--warm-up", type=int, default=200, help="untimed steps first (default 200)")
    parser.add_argument("--rate", type=float, default=20.0, help="steps per second (Hz, default 20)")
    parser.add_argument("--seed", type=int, default=0, help="the recorded episode is played from reset(seed=SEED)")
    parser.add_argument("--domain-id", type=int, default=40, help="ROS_DOMAIN_ID of this process and the node (default 40)")
    parser.add_argument("--note", default="", help="a line to print with the header (e.g. what else ran)")
    parser.add_argument(
        "--out", type=Path, nargs="?", const=OUT, default=None, help=f"also write the output to this file (default {OUT})"
    )
    args = parser.parse_args()
    if args.steps < 1 or args.warm_up < 0 or not args.rate > 0:
        parser.error(f"--steps must be >= 1, --warm-up >= 0 and --rate > 0, got {args.steps}, {args.warm_up}, {args.rate}")
    if not 0 <= args.domain_id <= 232:
        parser.error(f"--domain-id {args.domain_id} is not a ROS 2 domain id (0 to 232)")
    lines: list[str] = []

    def say(line: str) -> None:
        print(line, flush=True)
        lines.append(line)

    cores = sorted(os.sched_getaffinity(0))
    node_core, own_core = cores[0], cores[1 % len(cores)]
    load = " ".join(f"{value:.2f}" for value in os.getloadavg())
    os.environ["ROS_DOMAIN_ID"], os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = str(args.domain_id), "LOCALHOST"
    say(f"ros_latency: one agent node's scan-to-command time over ROS 2, safety filter on; {machine_line()}")
    say(f"  load average at the start: {load}")
    if args.note:
        say(f"  note: {args.note}")
    replay = record_episode(args.seed)
    count = args.warm_up + args.steps
    say(
        f"  inputs: the stage-3 episode of seed {args.seed} ({len(replay.steps)} steps; the filter changed "
        f"{replay.filter_changed:.1%} of agent {AGENT}'s actions), replayed in turn, {args.rate:g} Hz, odometry half a "
        "period before each scan"
    )
    pin(os.getpid(), own_core)
    seconds, commands, late = measure_over_ros(replay, count, args, (node_core, own_core), say)
    pin(os.getpid(), node_core)
    reference, expected, changed, near = in_process(replay, count)
    timed = slice(args.warm_up, None)
    ros, alone = percentiles(seconds[timed]), percentiles(reference[timed])
    say(f"  {f'{args.steps} steps after {args.warm_up} (ms)':<52}" + "".join(f"{name:>9}" for name in ros))
    for label, figures in (
        ("over ROS 2: scan published -> Twist received", ros),
        (f"in process, on core {node_core} after the node stopped", alone),
    ):
        say(f"  {label:<52}" + "".join(f"{value:9.3f}" for value in figures.values()))
    say(f"  ROS / in process: median {ros['median'] / alone['median']:.2f}x, p99 {ros['p99'] / alone['p99']:.2f}x")
    met = ros["median"] <= TARGET_MEDIAN and ros["p99"] <= TARGET_P99
    say(f"  target (median <= {TARGET_MEDIAN:g} ms, p99 <= {TARGET_P99:g} ms): {'met' if met else 'NOT met'}")
    difference = float(np.abs(commands - expected).max())
    say(
        f"  the node's commands against the in-process ones: largest difference {difference:.2e} m/s over {count} steps; "
        f"the filter changed {changed} of them, {near} saw an obstacle in range"
    )
    overdue = sum(k >= args.warm_up for k in late)
    say(f"  commands that came after the next step was due: {overdue} of {args.steps}")
    if args.out is not None:
        args.out.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
