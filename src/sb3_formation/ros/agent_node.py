"""The agent node: one robot's policy over ROS 2 (``docs/deployment.md``).

It reads its ``LaserScan``, every teammate's ``Odometry`` (its own among them) and the team's goal, hands their
arrays to the on-board pipeline (:class:`~sb3_formation.ros.onboard.Onboard`: observation, policy, safety filter,
command) when its inputs are in, and publishes the command as a ``Twist``. Every step it also publishes its message
(``JointState``: what a talking policy's agent sends its ring neighbours, empty for other policies), which is its
teammates' sign of life: a teammate whose messages fall silent for ``failed_after`` seconds has failed, and the robot
re-forms without it on the ring of the flying teammates (``docs/deployment.md``, "A teammate that fails"). A talking
policy's agent hears its ring neighbours' messages. A stale or missing input gives a zero
command and a logged warning, and so does an unusable one (a value that is not finite or out of bounds, a stamp from
the future, a scan too large, a second publisher on the command topic): the node never stops on its inputs and never
publishes a non-finite command. The node is a shell over :mod:`~sb3_formation.ros.onboard`, which holds every rule:
subscriptions, when to act, and messages to arrays and back.

Synchronous mode acts once per scan message, with its team's odometry of the scan's stamp (each teammate's last
``qos_depth`` odometry messages are kept): a scan delivered late (the simulator's observation delay) is seen with the
team as it was when the scan was taken, and acted on again when the same stamp comes again. Free mode acts on the
newest of every input, as a robot must (``docs/guarantees.md``).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import fields
from typing import Any, cast

import numpy as np
from geometry_msgs.msg import PointStamped, Twist
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import ParameterDescriptor  # type: ignore[import-not-found, unused-ignore]
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock as ClockMessage
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
from sb3_formation.ros.onboard import (
    AgentSettings,
    Onboard,
    Silence,
    TeamView,
    UnusableInput,
    command_problem,
    scan_size_problem,
    stamp_problem,
    typed_parameters,
)

#: Synchronous mode: a teammate without a message in this many steps the robot acted on has failed (``failed_after``).
MISSED_STEPS = 3
#: The goal's QoS: reliable and latched, so that a robot that starts late still gets the goal given before.
GOAL_QOS = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


def declared_settings(node: Node, settings: Any) -> dict[str, Any]:
    """Declare every field of a node's settings (a dataclass) as a ROS parameter of the node, its value the default;
    return the values the parameters have (``--ros-args -p name:=value`` overrides), as the settings' types
    (:func:`~sb3_formation.ros.onboard.typed_parameters`: an integer for a number is taken, another type is a
    one-line ``ValueError``, not rclpy's exception)."""
    anything = ParameterDescriptor(dynamic_typing=True)  # the type is checked in one line below
    values = {
        item.name: node.declare_parameter(item.name, getattr(settings, item.name), anything).value for item in fields(settings)
    }
    return typed_parameters(settings, values)


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
            #: the robot's pipeline: observation, policy, filter, command
            self.onboard = Onboard(policy, settings)
        except ValueError:  # a bad parameter override: no half-built node is left
            self.destroy_node()
            raise
        self.config = config = policy.config
        #: every teammate's newest odometry (the last to arrive), and its last ``qos_depth`` by stamp (ns)
        self.team: list[Odometry | None] = [None] * config.n_agents
        self.odometry: list[dict[int, Odometry]] = [{} for _ in range(config.n_agents)]
        self.scan: LaserScan | None = None
        self.goal: PointStamped | None = None
        self._goal_fresh = False
        self._scan_fresh = False  # synchronous mode: the scan has not been acted on
        #: every teammate's messages (their sign of life; a talking policy's agent reads its ring neighbours'):
        #: synchronous mode: those of this episode, in order, one per step the teammate acted on (stamp in ns,
        #: values; ``None``: an unusable message); free mode: the newest each sent
        self.teammates = [index for index in range(config.n_agents) if index != settings.agent]
        self._heard: dict[int, list[tuple[int, np.ndarray | None]]] = {index: [] for index in self.teammates}
        self._latest: dict[int, tuple[int, np.ndarray | None] | None] = dict.fromkeys(self.teammates)
        self._steps = 0  # synchronous mode: the steps the robot acted on in this episode
        self._heard_at: dict[int, int] = dict.fromkeys(self.teammates, 0)  # synchronous mode: the step of each one's last
        self._acted_at = 0  # the clock (ns) when the robot first acted in this episode
        self._listening_at = 0.0  # the wall-clock listening time (Silence) when it did
        #: wall-clock silence of each input; another publisher on the command topic (the watchdog looks)
        self._silence = Silence(2.0 / settings.watchdog_rate)
        self._crowded = False
        reliability = ReliabilityPolicy.BEST_EFFORT if settings.best_effort_sensors else ReliabilityPolicy.RELIABLE
        sensors = QoSProfile(depth=settings.qos_depth, reliability=reliability)
        self._scan_topic = self.create_subscription(LaserScan, settings.scan_topic, self._on_scan, sensors).topic_name
        self._odom_topics = [settings.odom_topic.format(index=index) for index in range(config.n_agents)]
        for index, topic in enumerate(self._odom_topics):
            self.create_subscription(Odometry, topic, lambda message, index=index: self._on_odometry(index, message), sensors)
        self.create_subscription(PointStamped, settings.goal_topic, self._on_goal, GOAL_QOS)
        self.commands = self.create_publisher(Twist, settings.cmd_topic, settings.qos_depth)
        topic = settings.observation_topic
        self.observations = self.create_publisher(Float32MultiArray, topic, settings.qos_depth) if topic else None
        self.messages = self.create_publisher(JointState, settings.message_topic, settings.qos_depth)
        for index in self.teammates:
            topic = settings.neighbour_message_topic.format(index=index)
            self.create_subscription(
                JointState, topic, lambda message, index=index: self._on_message(index, message), settings.qos_depth
            )
        if settings.synchronous:  # the simulator's sign of life while it waits for a step's commands
            self.create_subscription(ClockMessage, settings.clock_topic, lambda _: self._heard_input("clock"), 1)
        # on the wall clock: a stopped simulator or /clock still stops the robot
        self.create_timer(1.0 / settings.watchdog_rate, self._watch, clock=Clock(clock_type=ClockType.STEADY_TIME))

    # Inputs ---------------------------------------------------------------------------------------------------------

    def _heard_input(self, name: str) -> None:
        self._silence.heard(name, time.monotonic())

    def _on_scan(self, message: LaserScan) -> None:
        self.scan, self._scan_fresh = message, True
        self._heard_input("scan")
        if self.settings.synchronous:
            self._act_when_complete()
        else:
            self._act_if_fresh()

    def _on_odometry(self, index: int, message: Odometry) -> None:
        self.team[index] = message
        kept = self.odometry[index]
        kept[nanoseconds_of(message.header.stamp)] = message
        for old in sorted(kept)[: -self.settings.qos_depth]:
            del kept[old]
        self._heard_input(f"odometry {index}")
        if self.settings.synchronous:
            self._act_when_complete()

    def _on_goal(self, message: PointStamped) -> None:
        current = self.goal
        self._heard_input("goal")
        if current is None or (message.point.x, message.point.y, nanoseconds_of(message.header.stamp)) != (
            current.point.x,
            current.point.y,
            nanoseconds_of(current.header.stamp),
        ):  # a new goal: a new episode, whose messages are stamped from its start on
            self.onboard.reset()
            start = nanoseconds_of(message.header.stamp)
            self._heard = {index: [item for item in heard if item[0] >= start] for index, heard in self._heard.items()}
            self._latest, self._steps = dict.fromkeys(self.teammates), 0
            self._heard_at = dict.fromkeys(self.teammates, 0)
        self.goal, self._goal_fresh = message, True
        if self.settings.synchronous:
            self._act_when_complete()

    @property
    def neighbours(self) -> tuple[int, ...]:
        """The ring neighbours (preceding, succeeding) whose messages a talking policy's agent hears, on the ring of
        the flying teammates (none for other policies)."""
        return self.onboard.neighbours

    def _on_message(self, index: int, message: JointState) -> None:
        stamp, message_values = policy_message_of(message)
        values: np.ndarray | None = message_values
        self._heard_input(f"message {index}")
        size = self.onboard.message_size
        if message_values.shape != (size,) or not np.isfinite(message_values).all():
            self.get_logger().warning(
                f"agent {self.settings.agent}: a message of agent {index} is not {size} finite values: stopping until "
                "a usable one",
                throttle_duration_sec=1.0,
            )
            values = None
        self._latest[index] = stamp, values
        if self.settings.synchronous:
            if self.goal is not None and stamp < nanoseconds_of(self.goal.header.stamp):
                return  # the simulator's stamps: a message of an episode before the goal's
            self._heard[index].append((stamp, values))
            self._heard_at[index] = self._steps
            self._act_when_complete()

    # Teammates that fail -------------------------------------------------------------------------------------------

    def _flying_teammates(self) -> list[int]:
        return [index for index in self.teammates if self.onboard.flying[index]]

    def _find_failures(self) -> str:
        """Teammates that fell silent have failed: re-form without them (:meth:`~sb3_formation.ros.onboard.Onboard.fail`).
        Free mode: silent for ``failed_after`` seconds of this episode; synchronous mode: without a message in
        :data:`MISSED_STEPS` steps the robot acted on (the simulator steps only once every agent that flies has
        commanded, and each sends its message before its command, so steps without one are the simulator's failure:
        a pause of the whole loop is no one's). Return why the robot must stop instead (too few teammates left to fly a
        ring), or ``""``."""
        if not self.settings.failed_after or self.onboard.starting:
            return ""
        episode = self._silence.listening - self._listening_at
        for index in self._flying_teammates():
            if self.settings.synchronous:
                missed = self._steps - self._heard_at[index]
                silence = f"without a message in {missed} steps"
                if missed < MISSED_STEPS:
                    continue
            else:
                seconds = min(self._silence.silent_for(f"message {index}"), episode)
                silence = f"silent for {seconds:.1f} s"
                if seconds <= self.settings.failed_after:
                    continue
            try:
                self.onboard.fail(index)
            except ValueError as error:
                return f"agent {index} {silence} and {error}"
            self.get_logger().warning(
                f"agent {self.settings.agent}: agent {index} {silence} has failed: flying on without it (teammates "
                f"flying: {self._flying_teammates()})"
            )
        return ""

    # Acting -------------------------------------------------------------------------------------------------------

    def _act_when_complete(self) -> None:
        """Synchronous mode: act once per scan message, when every teammate's odometry of its stamp, a goal received
        since the last command and (a policy with messages, after the episode's first step) each ring neighbour's
        message of the step before are all in: a neighbour's k-th message of the episode is the one of the step
        before the robot's (k + 1)-th (a neighbour silent for ``failed_after`` seconds has failed: the watchdog
        looks, and the robot then waits for its new neighbour's)."""
        scan = self.scan
        if scan is None or not self._scan_fresh or not self._goal_fresh:
            return
        stamp = nanoseconds_of(scan.header.stamp)
        team = [kept.get(stamp) for kept in self.odometry]
        if any(odometry is None for odometry in team):
            return
        problem = self._find_failures()
        if problem:
            self._scan_fresh = False
            self._stop(problem)
            return
        starting, step = self.onboard.starting, self._steps
        if not starting and any(len(self._heard[index]) < step for index in self.neighbours):
            return  # a neighbour's message of the last step is still on its way
        received = None if starting else [self._heard[index][step - 1][1] for index in self.neighbours]
        self._scan_fresh = self._goal_fresh = False
        self._steps += 1
        problem = self._crowding() or self._frame_problem(team)
        if problem:
            self._stop(problem)
        elif received is not None and any(values is None for values in received):
            self._stop("a neighbour's message of the last step is unusable")
        else:
            self._act(scan, cast("list[Odometry]", team), received)

    def _act_if_fresh(self) -> None:
        """Free-running mode: act on every scan whose other inputs are within ``input_timeout`` of it."""
        problem = self._find_failures() or self._stale_input()
        if problem or self.scan is None:
            self._stop(problem)
        else:  # the newest message of each neighbour in this episode (none yet: zeros, as at an episode's start)
            size = self.onboard.message_size
            newest = [np.zeros(size) if latest is None else latest[1] for latest in map(self._latest.get, self.neighbours)]
            self._act(self.scan, cast("list[Odometry]", self.team), None if self.onboard.starting else newest)

    def _stale_input(self) -> str:
        """Free-running mode: what is missing, stale (older than ``input_timeout`` by its stamp and the node's clock,
        or not heard for that long on the wall clock), stamped in the future or otherwise unusable, or ``""``."""
        settings = self.settings
        now, timeout = self.get_clock().now().nanoseconds, settings.input_timeout
        problem = self._crowding()
        if problem:
            return problem
        if self.goal is None:
            return "no goal yet"
        scan, team = self.scan, self.team
        inputs = [
            (self._scan_topic, "scan", scan),
            *zip(self._odom_topics, (f"odometry {i}" for i in range(len(team))), team),
        ]
        for topic, name, message in inputs:
            if message is None or self._silence.silent_for(name) > timeout:
                return f"nothing on {topic} for {timeout:g} s"
            problem = stamp_problem(f"the message on {topic}", nanoseconds_of(message.header.stamp), now, settings)
            if problem:
                return problem
        problem = stamp_problem(
            f"the goal on {settings.goal_topic}", nanoseconds_of(self.goal.header.stamp), now, settings, False
        )
        if problem:
            return problem
        for index in self.neighbours:
            latest = self._latest[index]
            if self.onboard.starting:
                break
            topic = settings.neighbour_message_topic.format(index=index)
            if latest is None:  # nothing in this episode: silent since the robot's first action
                if now - self._acted_at > timeout * 1e9:
                    return f"no message of agent {index} on {topic} for {timeout:g} s"
                continue
            if latest[1] is None:
                return f"the last message of agent {index} on {topic} is unusable"
            problem = stamp_problem(f"the message of agent {index} on {topic}", latest[0], now, settings)
            if problem or self._silence.silent_for(f"message {index}") > timeout:
                return problem or f"no message of agent {index} on {topic} for {timeout:g} s"
        problem = self._frame_problem(team)
        if problem or scan is None:
            return problem
        try:
            self.onboard.check(*self._arrays(scan, cast("list[Odometry]", team)))
        except UnusableInput as unusable:
            return str(unusable)
        return ""

    def _crowding(self) -> str:
        if self._crowded:
            return (
                f"another node publishes on {self.commands.topic_name}: one robot, two pilots (a process left running, "
                "a robot started twice); stop one"
            )
        return ""

    def _frame_problem(self, team: Sequence[Odometry | None]) -> str:
        goal = self.goal
        frames = {message.header.frame_id for message in team if message is not None}
        frames |= {goal.header.frame_id} if goal is not None else set()
        if frames != {self.settings.world_frame}:
            return f"poses and goal must be in the world frame {self.settings.world_frame!r}, got {sorted(frames)}"
        return ""

    def _watch(self) -> None:
        """The watchdog (a wall-clock timer, every mode): another publisher on the command topic, teammates that failed;
        free mode: stale or unusable inputs; synchronous mode: nothing heard from the simulator for ``input_timeout``."""
        self._silence.tick(time.monotonic())
        self._crowded = self.count_publishers(self.commands.topic_name) > 1
        problem = self._find_failures()
        if not problem and self.settings.synchronous:
            self._act_when_complete()  # a teammate found failed may let the robot act on the scan it waits with
            if self._silence.ever_heard() and min(self._silence_of_all()) > self.settings.input_timeout:
                problem = f"nothing heard from the simulator for {self.settings.input_timeout:g} s"
        elif not problem:
            problem = self._stale_input()
        if problem:
            self._stop(problem)

    def _silence_of_all(self) -> list[float]:
        names = ["scan", "goal", "clock", *(f"odometry {i}" for i in range(len(self.team)))]
        return [self._silence.silent_for(name) for name in names] + [
            self._silence.silent_for(f"message {index}") for index in self.teammates
        ]

    def _stop(self, problem: str) -> None:
        """A zero command, and a warning (at most one a second) saying why."""
        self.commands.publish(Twist())
        self.get_logger().warning(f"agent {self.settings.agent} stopped: {problem}", throttle_duration_sec=1.0)

    def _arrays(self, scan: LaserScan, team: Sequence[Odometry]) -> tuple:
        """The inputs of :meth:`Onboard.step` (scan, team, forward speed, goal) from the messages (all present)."""
        problem = scan_size_problem(len(scan.ranges))  # before anything is allocated for it
        if problem:
            raise UnusableInput(problem)
        goal = self.goal
        if goal is None or len(team) < len(self.team) or any(message is None for message in team):
            raise RuntimeError("the agent node acted without a goal or a teammate's odometry")  # callers check first
        states = [odometry_state(message) for message in team]
        view = TeamView(*(np.array([state[part] for state in states]) for part in (0, 2, 1)))
        forward_speed = float(team[self.settings.agent].twist.twist.linear.x)
        return scan_of(scan), view, forward_speed, np.array([goal.point.x, goal.point.y])

    def _act(self, scan: LaserScan, team: Sequence[Odometry], received: Sequence[np.ndarray | None] | None) -> None:
        """Observe, act, filter and publish the command (and the message to the neighbours); an unusable input (the
        on-board checks) gives a zero command instead.

        :param team: every teammate's odometry paired with the scan
        :param received: what the preceding and succeeding neighbours sent at the last step (``None``: nothing yet)
        """
        if self.onboard.starting:
            self._acted_at, self._listening_at = self.get_clock().now().nanoseconds, self._silence.listening
        heard = None if received is None or not self.neighbours else np.stack(cast("list[np.ndarray]", received))
        stamp = nanoseconds_of(scan.header.stamp)
        try:
            inputs = self._arrays(scan, team)
            step = self.onboard.step(inputs[0], inputs[1], inputs[2], inputs[3], heard, stamp)
        except UnusableInput as unusable:
            self._stop(str(unusable))
            return
        view = inputs[1]
        self.messages.publish(policy_message(scan.header.stamp, step.message))  # a sign of life, whatever the policy
        twist = twist_message(step.command, self.onboard.dynamics, float(view.headings[self.settings.agent]))
        problem = command_problem(
            (twist.linear.x, twist.linear.y, twist.linear.z, twist.angular.x, twist.angular.y, twist.angular.z)
        )
        if problem:  # the last check before publishing
            self._stop(problem)
            return
        self.commands.publish(twist)
        if self.observations is not None:
            self.observations.publish(Float32MultiArray(data=step.row.tolist()))
