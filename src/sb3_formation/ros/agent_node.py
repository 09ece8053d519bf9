"""The agent node: one robot's policy over ROS 2 (``docs/deployment.md``).

It reads its ``LaserScan``, every teammate's ``Odometry`` (its own among them) and the team's goal, builds the
observation on board (:mod:`~sb3_formation.ros.scans`, :mod:`~sb3_formation.ros.observer`), runs the exported policy
(:class:`~sb3_formation.runtime.OnnxPolicy`) and the safety filter, and publishes its command as a ``Twist``. A policy
whose agents send messages also hears its two ring neighbours' messages and sends its own (``JointState``). A stale
or missing input gives a zero command and a logged warning.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from geometry_msgs.msg import PointStamped, Twist
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState, LaserScan
from std_msgs.msg import Float32MultiArray

from sb3_formation.env.geometry import ring_neighbours
from sb3_formation.ros.messages import (
    nanoseconds_of,
    odometry_state,
    policy_message,
    policy_message_of,
    scan_of,
    twist_message,
)
from sb3_formation.ros.observer import FINAL_STAGE, AgentObserver, TeamView, velocity_command
from sb3_formation.ros.scans import ScanMount, resample_scan, split_scan
from sb3_formation.runtime import OnnxPolicy
from sb3_formation.safety.filter import SafetyFilter, SafetyGains
from sb3_formation.utils.checks import is_count, is_integer, is_number


@dataclass(frozen=True)
class AgentSettings:
    """The agent node's ROS parameters and their defaults (each is also a ROS parameter of the node, same name).

    :param agent: the robot's index in its team (ring order)
    :param world_frame: the frame shared by the team, of every pose and of the goal (REP 105's ``map``)
    :param scan_topic: the robot's ``LaserScan``
    :param odom_topic: every teammate's ``Odometry``, ``{index}`` standing for its index (the robot's own among them)
    :param goal_topic: the team's goal (``PointStamped``, latched)
    :param cmd_topic: where the robot's command goes (``Twist``)
    :param observation_topic: where the observation is published (``Float32MultiArray``), ``""``: not published
    :param message_topic: where the robot's message to its ring neighbours goes (``JointState``; a policy whose agents
        send messages only)
    :param neighbour_message_topic: a ring neighbour's message topic, ``{index}`` standing for its index
    :param scan_x: the scanner's position (m) ahead of the robot's centre, in its base frame
    :param scan_y: the scanner's position (m) left of the robot's centre
    :param scan_yaw: the scanner's yaw (rad) in the robot's base frame
    :param max_gap: (m) neighbouring returns at most this far apart are one surface (:func:`resample_scan`)
    :param agent_tolerance: (m) a return this close to a teammate's disc is that teammate (:func:`split_scan`)
    :param input_timeout: (s) an input older than this is stale: the robot stops
    :param watchdog_rate: (Hz) how often stale inputs are looked for between scans
    :param synchronous: act only on a scan and every teammate's odometry of one stamp and a goal received since the
        last command (the simulator's synchronous mode: one command per step, deterministic); no watchdog
    :param safety_filter: filter the actions (the policy's own gains if it was trained behind the filter, else the
        defaults)
    :param stage: the curriculum stage whose reward coefficients the observed previous reward uses
    :param qos_depth: the history depth of every subscription and publisher
    :param best_effort_sensors: subscribe to scans and odometry best effort (a scanner driver's sensor-data QoS)
    """

    agent: int = 0
    world_frame: str = "map"
    scan_topic: str = "scan"
    odom_topic: str = "/agent_{index}/odom"
    goal_topic: str = "/goal"
    cmd_topic: str = "cmd_vel"
    observation_topic: str = ""
    message_topic: str = "message"
    neighbour_message_topic: str = "/agent_{index}/message"
    scan_x: float = 0.0
    scan_y: float = 0.0
    scan_yaw: float = 0.0
    max_gap: float = 0.1
    agent_tolerance: float = 0.05
    input_timeout: float = 1.0
    watchdog_rate: float = 10.0
    synchronous: bool = False
    safety_filter: bool = True
    stage: int = FINAL_STAGE
    qos_depth: int = 10
    best_effort_sensors: bool = False

    def __post_init__(self) -> None:
        positive = ("max_gap", "input_timeout", "watchdog_rate")
        for name in positive:
            if not (is_number(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name} must be a number > 0, got {getattr(self, name)!r}")
        if not (is_number(self.agent_tolerance) and self.agent_tolerance >= 0):
            raise ValueError(f"agent_tolerance must be a number >= 0, got {self.agent_tolerance!r}")
        if not is_count(self.agent) or not (is_integer(self.qos_depth) and self.qos_depth >= 1):
            raise ValueError(f"agent must be an integer >= 0 and qos_depth >= 1, got {self.agent!r} and {self.qos_depth!r}")
        if self.stage not in (1, 2, 3):
            raise ValueError(f"stage must be 1, 2 or 3, got {self.stage!r}")
        for name in ("odom_topic", "neighbour_message_topic"):
            if "{index}" not in getattr(self, name):
                raise ValueError(f"{name} must hold {{index}} where a teammate's index goes, got {getattr(self, name)!r}")


#: The goal's QoS: reliable and latched, so that a robot that starts late still gets the goal given before.
GOAL_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def declared_settings(node: Node, settings: Any) -> dict[str, Any]:
    """Declare every field of a node's settings (a dataclass) as a ROS parameter of the node, its value the default;
    return the values the parameters have (``--ros-args -p name:=value`` overrides)."""
    return {item.name: node.declare_parameter(item.name, getattr(settings, item.name)).value for item in fields(settings)}


class AgentNode(Node):  # type: ignore[misc]  # rclpy's Node is untyped here
    """One robot's policy as a ROS 2 node (see the module docstring and :class:`AgentSettings`).

    :param policy: the exported policy (one session may serve the nodes of a whole team)
    :param settings: the defaults of the node's ROS parameters (``--ros-args -p name:=value`` overrides them)
    :param name: the node's name
    :param namespace: the node's namespace (its relative topics live there), e.g. ``agent_0``
    :param kwargs: further ``rclpy.node.Node`` arguments (``context``, ``parameter_overrides``)
    """

    def __init__(
        self, policy: OnnxPolicy, settings: AgentSettings, name: str = "formation_agent", namespace: str = "", **kwargs: Any
    ) -> None:
        super().__init__(name, namespace=namespace, **kwargs)
        try:
            self.settings = settings = AgentSettings(**declared_settings(self, settings))
        except ValueError:  # a bad parameter override: no half-built node is left
            self.destroy_node()
            raise
        self.config = config = policy.config
        self.observer = AgentObserver(config, settings.agent, settings.stage)
        own = policy.safety
        self.policy = policy.without_filter()
        gains = own.gains if own is not None else SafetyGains()
        #: the filter every action passes through (``None`` with ``safety_filter`` off)
        self.filter = SafetyFilter(config, gains) if settings.safety_filter else None
        self.mount = ScanMount(settings.scan_x, settings.scan_y, settings.scan_yaw)
        self.team: list[Odometry | None] = [None] * config.n_agents
        self.scan: LaserScan | None = None
        self.goal: PointStamped | None = None
        self._goal_fresh = False
        self._acted_stamp = -1
        self._state: Any = None
        self._starting = True
        #: the ring neighbours (preceding, succeeding) whose messages the robot hears, and what each sent, by stamp (ns)
        ring = ring_neighbours(config.n_agents)[settings.agent]
        self.neighbours = tuple(int(index) for index in ring) if policy.metadata.message_size else ()
        self._heard: list[dict[int, np.ndarray]] = [{} for _ in self.neighbours]
        self._acted_at = 0  # the clock (ns) when the robot first acted in this episode
        reliability = ReliabilityPolicy.BEST_EFFORT if settings.best_effort_sensors else ReliabilityPolicy.RELIABLE
        sensors = QoSProfile(depth=settings.qos_depth, reliability=reliability)
        self._scan_topic = self.create_subscription(LaserScan, settings.scan_topic, self._on_scan, sensors).topic_name
        for index in range(config.n_agents):
            topic = settings.odom_topic.format(index=index)
            self.create_subscription(Odometry, topic, lambda message, index=index: self._on_odometry(index, message), sensors)
        self.create_subscription(PointStamped, settings.goal_topic, self._on_goal, GOAL_QOS)
        self.commands = self.create_publisher(Twist, settings.cmd_topic, settings.qos_depth)
        topic = settings.observation_topic
        self.observations = self.create_publisher(Float32MultiArray, topic, settings.qos_depth) if topic else None
        self.messages = (
            self.create_publisher(JointState, settings.message_topic, settings.qos_depth) if self.neighbours else None
        )
        for slot, index in enumerate(self.neighbours):
            topic = settings.neighbour_message_topic.format(index=index)
            self.create_subscription(
                JointState, topic, lambda message, slot=slot: self._on_message(slot, message), settings.qos_depth
            )
        if not settings.synchronous:
            self.create_timer(1.0 / settings.watchdog_rate, self._watch)

    # Inputs ---------------------------------------------------------------------------------------------------------

    def _on_scan(self, message: LaserScan) -> None:
        self.scan = message
        if self.settings.synchronous:
            self._act_when_complete()
        else:
            self._act_if_fresh()

    def _on_odometry(self, index: int, message: Odometry) -> None:
        self.team[index] = message
        if self.settings.synchronous:
            self._act_when_complete()

    def _on_goal(self, message: PointStamped) -> None:
        current = self.goal
        if current is None or (message.point.x, message.point.y, nanoseconds_of(message.header.stamp)) != (
            current.point.x,
            current.point.y,
            nanoseconds_of(current.header.stamp),
        ):  # a new goal: a new episode
            self.observer.reset()
            self._state, self._starting = None, True
            for heard in self._heard:
                heard.clear()
        self.goal, self._goal_fresh = message, True
        if self.settings.synchronous:
            self._act_when_complete()

    def _on_message(self, slot: int, message: JointState) -> None:
        stamp, values = policy_message_of(message)
        size = self.policy.metadata.message_size
        if values.shape != (size,) or not np.isfinite(values).all():
            index = self.neighbours[slot]
            self.get_logger().warning(f"ignored a message of agent {index}: not {size} finite values")
            return
        heard = self._heard[slot]
        heard[stamp] = values
        for old in sorted(heard)[: -self.settings.qos_depth]:
            del heard[old]
        if self.settings.synchronous:
            self._act_when_complete()

    # Acting -------------------------------------------------------------------------------------------------------

    def _act_when_complete(self) -> None:
        """Synchronous mode: act once per stamp, when the scan, every teammate's odometry of its stamp and a goal
        received since the last command are all in."""
        scan = self.scan
        if scan is None or not self._goal_fresh:
            return
        stamp = nanoseconds_of(scan.header.stamp)
        if stamp == self._acted_stamp or any(
            odometry is None or nanoseconds_of(odometry.header.stamp) != stamp for odometry in self.team
        ):
            return
        if not self._starting and any(self._acted_stamp not in heard for heard in self._heard):
            return  # a neighbour's message of the last step is still on its way
        received = None if self._starting else [heard[self._acted_stamp] for heard in self._heard]
        self._acted_stamp, self._goal_fresh = stamp, False
        self._act(scan, received)

    def _act_if_fresh(self) -> None:
        """Free-running mode: act on every scan whose other inputs are within ``input_timeout`` of it."""
        problem = self._stale_input()
        if problem:
            self._stop(problem)
        else:  # the newest message of each neighbour in this episode (none yet: zeros, as at an episode's start)
            newest = [heard[max(heard)] if heard else np.zeros(self.policy.metadata.message_size) for heard in self._heard]
            self._act(self.scan, None if self._starting else newest)

    def _stale_input(self) -> str:
        """What is missing or older than ``input_timeout`` (by the node's clock), or ``""``."""
        now, timeout = self.get_clock().now().nanoseconds, self.settings.input_timeout * 1e9
        if self.goal is None:
            return "no goal yet"
        if self.scan is None or now - nanoseconds_of(self.scan.header.stamp) > timeout:
            return f"no scan on {self._scan_topic} for {self.settings.input_timeout} s"
        for index, odometry in enumerate(self.team):
            if odometry is None or now - nanoseconds_of(odometry.header.stamp) > timeout:
                topic = self.settings.odom_topic.format(index=index)
                return f"no odometry of agent {index} on {topic} for {self.settings.input_timeout} s"
        for index, heard in zip(self.neighbours, self._heard):
            last = max(heard) if heard else self._acted_at  # from the robot's first action of the episode
            if not self._starting and now - last > timeout:
                topic = self.settings.neighbour_message_topic.format(index=index)
                return f"no message of agent {index} on {topic} for {self.settings.input_timeout} s"
        return ""

    def _watch(self) -> None:
        problem = self._stale_input()
        if problem:
            self._stop(problem)

    def _stop(self, problem: str) -> None:
        """A zero command, and a warning (at most one a second) saying why."""
        self.commands.publish(Twist())
        self.get_logger().warning(f"agent {self.settings.agent} stopped: {problem}", throttle_duration_sec=1.0)

    def _act(self, scan: LaserScan, received: list[np.ndarray] | None) -> None:
        """Observe, act, filter and publish the command (and the message to the neighbours).

        :param received: what the preceding and succeeding neighbours sent at the last step (``None``: nothing yet)
        """
        goal, team = self.goal, [message for message in self.team if message is not None]
        if goal is None or len(team) < len(self.team):  # the callers act only with every input in
            raise RuntimeError("the agent node acted without a goal or a teammate's odometry")
        frames = {message.header.frame_id for message in team} | {goal.header.frame_id}
        if frames != {self.settings.world_frame}:
            self._stop(f"poses and goal must be in the world frame {self.settings.world_frame!r}, got {sorted(frames)}")
            return
        config, agent = self.config, self.settings.agent
        states = [odometry_state(message) for message in team]
        positions = np.array([state[0] for state in states])
        headings = np.array([state[1] for state in states])
        velocities = np.array([state[2] for state in states])
        readings = resample_scan(scan_of(scan), self.mount, float(headings[agent]), config, self.settings.max_gap)
        lidar = split_scan(readings, config, positions, agent, self.settings.agent_tolerance)
        target = np.array([goal.point.x, goal.point.y])
        row = self.observer.observe(TeamView(positions, velocities, headings), lidar, target).astype(np.float32)[None, :]
        start = np.array([self._starting])
        heard = None if received is None or not self.neighbours else np.stack(received)[None]
        step = self.policy.agent_step(row, np.array([agent]), self._state, start, heard)
        action, self._state = step.actions, step.state
        if self.filter is not None:
            action = self.filter.filter(row, action)[0]
        if self._starting:
            self._acted_at = self.get_clock().now().nanoseconds
        self._starting = False
        if self.messages is not None:
            self.messages.publish(policy_message(scan.header.stamp, step.messages[0]))
        self.observer.remember(action[0])
        forward_speed = float(team[agent].twist.twist.linear.x)
        command = velocity_command(config, action[0], velocities[agent], forward_speed)
        self.commands.publish(twist_message(command, config.dynamics, float(headings[agent])))
        if self.observations is not None:
            self.observations.publish(Float32MultiArray(data=row[0].tolist()))
