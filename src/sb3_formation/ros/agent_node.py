"""The agent node: one robot's policy over ROS 2 (``docs/deployment.md``).

It reads its ``LaserScan``, every teammate's ``Odometry`` (its own among them) and the team's goal, hands their
arrays to the on-board pipeline (:class:`~sb3_formation.ros.onboard.Onboard`: observation, policy, safety filter,
command) when its inputs are in, and publishes the command as a ``Twist``. A policy whose agents send messages also
hears its two ring neighbours' messages and sends its own (``JointState``). A stale or missing input gives a zero
command and a logged warning. The node is a shell over :mod:`~sb3_formation.ros.onboard`: subscriptions, when to act,
and messages to arrays and back.
"""

from __future__ import annotations

from dataclasses import fields
from typing import Any

import numpy as np
from geometry_msgs.msg import PointStamped, Twist
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import JointState, LaserScan
from std_msgs.msg import Float32MultiArray

from sb3_formation.controllers.base import TeamPolicy
from sb3_formation.ros.messages import (
    nanoseconds_of,
    odometry_state,
    policy_message,
    policy_message_of,
    scan_of,
    twist_message,
)
from sb3_formation.ros.onboard import AgentSettings, Onboard, TeamView

#: The goal's QoS: reliable and latched, so that a robot that starts late still gets the goal given before.
GOAL_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def declared_settings(node: Node, settings: Any) -> dict[str, Any]:
    """Declare every field of a node's settings (a dataclass) as a ROS parameter of the node, its value the default;
    return the values the parameters have (``--ros-args -p name:=value`` overrides)."""
    return {item.name: node.declare_parameter(item.name, getattr(settings, item.name)).value for item in fields(settings)}


class AgentNode(Node):  # type: ignore[misc]  # rclpy's Node is untyped here
    """One robot's policy as a ROS 2 node (see the module docstring and :class:`AgentSettings`).

    :param policy: the policy (:func:`~sb3_formation.runtime.load_onnx_policy`'s; one may serve a whole team's nodes)
    :param settings: the defaults of the node's ROS parameters (``--ros-args -p name:=value`` overrides them)
    :param name: the node's name
    :param namespace: the node's namespace (its relative topics live there), e.g. ``agent_0``
    :param kwargs: further ``rclpy.node.Node`` arguments (``context``, ``parameter_overrides``)
    """

    def __init__(
        self, policy: TeamPolicy, settings: AgentSettings, name: str = "formation_agent", namespace: str = "", **kwargs: Any
    ) -> None:
        super().__init__(name, namespace=namespace, **kwargs)
        try:
            self.settings = settings = AgentSettings(**declared_settings(self, settings))
        except ValueError:  # a bad parameter override: no half-built node is left
            self.destroy_node()
            raise
        try:
            #: the robot's pipeline: observation, policy, filter, command
            self.onboard = Onboard(policy, settings)
        except ValueError:
            self.destroy_node()
            raise
        self.config = config = policy.config
        self.team: list[Odometry | None] = [None] * config.n_agents
        self.scan: LaserScan | None = None
        self.goal: PointStamped | None = None
        self._goal_fresh = False
        self._acted_stamp = -1
        #: the ring neighbours (preceding, succeeding) whose messages the robot hears, and what each sent, by stamp (ns)
        self.neighbours = self.onboard.neighbours
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
            self.onboard.reset()
            for heard in self._heard:
                heard.clear()
        self.goal, self._goal_fresh = message, True
        if self.settings.synchronous:
            self._act_when_complete()

    def _on_message(self, slot: int, message: JointState) -> None:
        stamp, values = policy_message_of(message)
        size = self.onboard.message_size
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
        starting = self.onboard.starting
        if not starting and any(self._acted_stamp not in heard for heard in self._heard):
            return  # a neighbour's message of the last step is still on its way
        received = None if starting else [heard[self._acted_stamp] for heard in self._heard]
        self._acted_stamp, self._goal_fresh = stamp, False
        self._act(scan, received)

    def _act_if_fresh(self) -> None:
        """Free-running mode: act on every scan whose other inputs are within ``input_timeout`` of it."""
        problem = self._stale_input()
        if problem:
            self._stop(problem)
        else:  # the newest message of each neighbour in this episode (none yet: zeros, as at an episode's start)
            newest = [heard[max(heard)] if heard else np.zeros(self.onboard.message_size) for heard in self._heard]
            self._act(self.scan, None if self.onboard.starting else newest)

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
            if not self.onboard.starting and now - last > timeout:
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
        agent = self.settings.agent
        states = [odometry_state(message) for message in team]
        view = TeamView(*(np.array([state[part] for state in states]) for part in (0, 2, 1)))
        goal_point = np.array([goal.point.x, goal.point.y])
        if self.onboard.starting:
            self._acted_at = self.get_clock().now().nanoseconds
        heard = None if received is None or not self.neighbours else np.stack(received)
        step = self.onboard.step(scan_of(scan), view, float(team[agent].twist.twist.linear.x), goal_point, heard)
        if self.messages is not None:
            self.messages.publish(policy_message(scan.header.stamp, step.message))
        self.commands.publish(twist_message(step.command, self.onboard.dynamics, float(view.headings[agent])))
        if self.observations is not None:
            self.observations.publish(Float32MultiArray(data=step.row.tolist()))
