"""The simulator as a ROS 2 node: one team of the package's engine, flown through topics (``docs/deployment.md``).

Per agent i it publishes ``/agent_{i}/odom`` (``Odometry``: pose in the world frame, twist in the agent's body frame)
and ``/agent_{i}/scan`` (``LaserScan`` of a scanner at the agent's centre, :func:`~sb3_formation.ros.scans.merged_scan`),
the team's goal on ``/goal`` (``PointStamped``, latched, stamped with the sim time its episode started) and the sim time
on ``/clock``: steps played since the node started x dt, continuous across episodes. It applies each agent's
``/agent_{i}/cmd_vel`` (``Twist``) as the action that gives that command
(:meth:`~sb3_formation.env.dynamics.DynamicsModel.action`). Each step publishes the clock, the goal, every odometry, then
every scan, all stamped with the step's sim time (the goal with its episode's start).

Synchronous mode (the default) steps once every agent has sent a command since the last publication, so a closed loop
is as deterministic as an in-process one; free-running mode steps at ``rate`` times real time with the latest command
of each agent. The stamps are sim time: a node that judges its inputs' age by its clock (a free-running agent node)
runs with ``use_sim_time``. Episode k is played from ``reset(seed=seed + k)``, as ``sb3-formation evaluate`` plays its
episodes, and recorded (:class:`EpisodeRecord`) for comparison with an evaluation.

Under disturbances (:attr:`SimSettings.disturbances`, the task's ``disturbances`` section: a profile's name or a file)
the engine applies the motors' errors and the action delays to the actions it recovers, as in process, and the node
publishes what the agents sensed (:mod:`~sb3_formation.ros.sensing`): odometry of the position, heading and velocity
estimates, scans with the heading error's turn, the range errors and the dropped beams. An agent's observation delay
d (drawn per episode by the engine) delivers its scan of d steps before, with that step's stamp (the reset's while the
episode is younger); the odometry is published at once, and an agent node pairs a scan with its team's odometry of
the scan's stamp, so that everything the agent acts on is d steps old. A command is read back into an action
(:meth:`~sb3_formation.env.dynamics.DynamicsModel.action`) from the velocity, heading and forward speed the agent's
own odometry of that stamp gave it: the action is the one the agent chose.

While it waits for a step's commands, the synchronous mode publishes the clock again every :data:`WATCH_PERIOD` (the
same time): the agents' watchdogs hear the simulator alive, and stop their robots once it stops. In either mode a
command topic with two publishers stops the node in one line, and a command that is not finite is taken as a zero
command, with a warning.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, NamedTuple, cast

import numpy as np
from geometry_msgs.msg import PointStamped, Twist
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMessage
from sensor_msgs.msg import LaserScan

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.disturbances import load_disturbances
from sb3_formation.env.formation_env import FormationEnv
from sb3_formation.ros.agent_node import GOAL_QOS, declared_settings
from sb3_formation.ros.messages import goal_message, odometry_message, scan_message, stamp_of, twist_command
from sb3_formation.ros.onboard import check_disturbances
from sb3_formation.ros.sensing import Deliveries, PublishedTeam, published_team
from sb3_formation.utils.checks import is_count, is_integer, is_number
from sb3_formation.utils.files import atomic_path

#: (s) wall-clock period of the node's checks: two publishers on a command topic; synchronous mode: are the agents up,
#: has a command timed out (and the clock published again, a sign of life)
WATCH_PERIOD = 0.1


@dataclass(frozen=True)
class SimSettings:
    """The simulator node's ROS parameters and their defaults (each is also a ROS parameter of the node, same name).

    Topic and frame names hold ``{index}`` where an agent's index goes.

    :param seed: episode k is played from ``reset(seed=seed + k)`` (``sb3-formation evaluate``'s seeding)
    :param episodes: episodes to play; then the node stops stepping and sets ``done``
    :param synchronous: step once every agent has sent a command since the last publication (deterministic), starting
        once every command topic has a publisher and every odometry and scan topic a subscriber; else step at ``rate``
        times real time from the start with the latest command of each agent (none yet: a zero velocity command)
    :param rate: free-running mode's speed, in times real time: a step every dt / rate wall-clock seconds
    :param command_timeout: (s, wall clock) synchronous mode fails when an agent sends no command for this long after
        a publication
    :param failed_after: (s, wall clock) synchronous mode: an agent that has sent commands before and then none for
        this long after a publication has failed (its node died): its motors stop for the rest of the episode
        (:meth:`~sb3_formation.env.engine.FormationEngine.fail`: a passive body, an obstacle to the others' lidars)
        and the simulator steps on without it, as its teammates re-form without it; in the next episode it fails
        again once silent this long; 0: never (``command_timeout`` then fails the simulator)
    :param world_frame: the frame of every pose and of the goal (REP 105's ``map``)
    :param base_frame: each agent's body frame, of its scan and the child frame of its odometry
    :param odom_topic: each agent's ``Odometry``
    :param scan_topic: each agent's ``LaserScan``
    :param cmd_topic: each agent's command (``Twist``)
    :param goal_topic: the team's goal (``PointStamped``, latched)
    :param clock_topic: the sim time (``rosgraph_msgs/Clock``)
    :param qos_depth: the history depth of every publisher and subscription but the goal's (1)
    :param see_through_agents: the scans see through the agents, as the simulator's own lidar does (a check of the
        nodes: their observations are then the simulator's); default off: agents stop the beams, as for a real scanner
    :param disturbances: the episodes' disturbances: a profile's name (``ideal``, ``realistic``, ``harsh``) or a YAML
        file (:func:`~sb3_formation.env.disturbances.load_disturbances`); they replace the task's own, as
        ``sb3-formation evaluate --disturbances`` does
    """

    seed: int = 0
    episodes: int = 1
    synchronous: bool = True
    rate: float = 1.0
    command_timeout: float = 30.0
    failed_after: float = 5.0
    world_frame: str = "map"
    base_frame: str = "agent_{index}/base_link"
    odom_topic: str = "/agent_{index}/odom"
    scan_topic: str = "/agent_{index}/scan"
    cmd_topic: str = "/agent_{index}/cmd_vel"
    goal_topic: str = "/goal"
    clock_topic: str = "/clock"
    qos_depth: int = 10
    see_through_agents: bool = False
    disturbances: str = "ideal"

    def __post_init__(self) -> None:
        check_disturbances("disturbances", self.disturbances)
        if not is_count(self.seed):
            raise ValueError(f"seed must be an integer >= 0, got {self.seed!r}")
        if not (is_integer(self.episodes) and self.episodes >= 1):
            raise ValueError(f"episodes must be an integer >= 1, got {self.episodes!r}")
        for name in ("rate", "command_timeout"):
            value = getattr(self, name)
            if not (is_number(value) and value > 0):
                raise ValueError(f"{name} must be a number > 0, got {value!r}")
        if not (is_number(self.failed_after) and self.failed_after >= 0):
            raise ValueError(f"failed_after must be a number >= 0, got {self.failed_after!r}")
        if not (is_integer(self.qos_depth) and self.qos_depth >= 1):
            raise ValueError(f"qos_depth must be an integer >= 1, got {self.qos_depth!r}")
        for name in ("base_frame", "odom_topic", "scan_topic", "cmd_topic"):
            if "{index}" not in getattr(self, name):
                raise ValueError(f"{name} must hold {{index}} where an agent's index goes, got {getattr(self, name)!r}")


class EpisodeRecord(NamedTuple):
    """One episode the node played."""

    seed: int  #: it was played from ``reset(seed=seed)``
    success: bool  #: the centroid reached the goal (terminated)
    steps: int  #: steps played
    positions: np.ndarray  #: ``(steps + 1, n, 2)`` every agent's position (m) from the reset on


class SimNode(Node):  # type: ignore[misc]  # rclpy's Node is untyped here
    """One team of :class:`~sb3_formation.env.formation_env.FormationEnv` as a ROS 2 node (see the module docstring
    and :class:`SimSettings`). Spin it (:meth:`spin_until_done`) until :attr:`done`; :attr:`results` holds the
    episodes played.

    :param config: the task of the episodes: an exported policy's ``config`` with the stage and scenes to play, e.g.
        ``policy.config.replace(stage=3)`` (evaluations' stage); its disturbances are the settings' (default ideal,
        whatever ``config`` holds)
    :param settings: the defaults of the node's ROS parameters (``--ros-args -p name:=value`` overrides them)
    :param name: the node's name
    :param kwargs: further ``rclpy.node.Node`` arguments (``context``, ``namespace``, ``parameter_overrides``)
    :raises ValueError: scenes that cannot place the team, bad settings (both before any ROS entity is made), or bad
        parameter overrides (the node is destroyed)
    """

    def __init__(
        self, config: FormationConfig, settings: SimSettings | None = None, name: str = "formation_sim", **kwargs: Any
    ):
        settings = SimSettings() if settings is None else settings
        task = config
        # unknown scenes, or scenes that cannot place the team, fail here
        env = FormationEnv(task.replace(disturbances=load_disturbances(settings.disturbances)))
        super().__init__(name, **kwargs)
        try:
            values = declared_settings(self, settings)
            changed = settings if values == asdict(settings) else SimSettings(**values)
            if changed.disturbances != settings.disturbances:
                env = FormationEnv(task.replace(disturbances=load_disturbances(changed.disturbances)))
            settings = changed
        except ValueError:
            self.destroy_node()
            raise
        self.settings, self.env = settings, env
        self.config = config = env.config
        n_agents = config.n_agents
        #: the episodes played, in order
        self.results: list[EpisodeRecord] = []
        #: all episodes are played: the node steps no more
        self.done = False
        self._rows = env.engine.team_rows(env.team)
        self._steps_played = 0  # since the node started: the sim time in steps
        self._episode = -1
        self._episode_stamp = stamp_of(0.0)
        self._positions: list[np.ndarray] = []
        self._commands = [Twist() for _ in range(n_agents)]
        self._received = np.zeros(n_agents, dtype=np.int64)  # commands per agent since the last publication
        self._commanded = np.zeros(n_agents, dtype=bool)  # agents that ever sent a command
        self.failed = np.zeros(n_agents, dtype=bool)  #: agents that failed in this episode (``failed_after``)
        self._published_at = 0.0  # time.monotonic() of the last publication
        self._turn_rates = np.zeros(n_agents)  # a unicycle's turn rates (rad/s) of the last step
        #: each step's publication in this episode: what each agent gets under its observation delay
        self._deliveries: Deliveries[tuple[PublishedTeam, list[LaserScan]]] = Deliveries()
        self._frames = [settings.base_frame.format(index=index) for index in range(n_agents)]
        depth = settings.qos_depth
        self._clock = self.create_publisher(ClockMessage, settings.clock_topic, depth)
        self._odometry = [self.create_publisher(Odometry, settings.odom_topic.format(index=i), depth) for i in range(n_agents)]
        self._scans = [self.create_publisher(LaserScan, settings.scan_topic.format(index=i), depth) for i in range(n_agents)]
        self._goal = self.create_publisher(PointStamped, settings.goal_topic, GOAL_QOS)
        self._command_topics = [settings.cmd_topic.format(index=index) for index in range(n_agents)]
        self._subscriptions = [
            self.create_subscription(Twist, topic, lambda message, index=index: self._on_command(index, message), depth)
            for index, topic in enumerate(self._command_topics)
        ]
        wall = Clock(clock_type=ClockType.STEADY_TIME)
        self._watch_timer = self.create_timer(WATCH_PERIOD, self._watch, clock=wall)
        if not settings.synchronous:
            self._start_episode()
            self._timer = self.create_timer(config.dt / settings.rate, self._advance, clock=wall)

    # Running ------------------------------------------------------------------------------------------------------

    def spin_until_done(self, executor: Executor | None = None, timeout_sec: float = WATCH_PERIOD) -> None:
        """Spin until every episode is played (or the node's context shuts down).

        :param executor: an executor that holds this node (and any others, e.g. agent nodes); default: one of its own
        :param timeout_sec: (s) the longest wait of each spin for work
        """
        if executor is None:
            executor = SingleThreadedExecutor(context=self.context)
            executor.add_node(self)
        while not self.done and self.context.ok():
            executor.spin_once(timeout_sec=timeout_sec)

    def _watch(self) -> None:
        """Fail when a command topic has several publishers (another process flies an agent of the same index in this
        domain); synchronous mode: start once every agent is up, fail when an agent keeps its command too long, and
        publish the clock again while waiting (the agents' watchdogs hear the simulator alive)."""
        if self.done:
            return
        crowded = [
            topic
            for topic, subscription in zip(self._command_topics, self._subscriptions)
            if subscription.get_publisher_count() > 1
        ]
        if crowded:
            raise RuntimeError(
                f"several publishers on {', '.join(crowded)}: another process flies these agents in ROS domain "
                f"{os.environ.get('ROS_DOMAIN_ID', '0')}; stop it or choose another --domain-id"
            )
        if not self.settings.synchronous:
            return
        if self._episode < 0:
            missing = self._absent_topics()
            if missing:
                self.get_logger().info(f"waiting for the agents on {', '.join(missing)}", throttle_duration_sec=5.0)
            else:
                self._start_episode()
            return
        self._clock.publish(ClockMessage(clock=stamp_of(self._steps_played * self.config.dt)))
        waited = time.monotonic() - self._published_at
        if self.settings.failed_after and waited > self.settings.failed_after:
            self._fail_silent_agents(waited)
        if waited > self.settings.command_timeout:
            silent = np.flatnonzero((self._received == 0) & ~self.failed).tolist()
            raise TimeoutError(
                f"no command from agents {silent} (on {', '.join(self._command_topics[i] for i in silent)}) within "
                f"{self.settings.command_timeout} s of step {self.env.step_count} of episode {self._episode}"
            )

    def _absent_topics(self) -> list[str]:
        """The topics whose other end is not up yet: commands without a publisher, odometry and scans without a
        subscriber."""
        commands = [
            topic
            for topic, subscription in zip(self._command_topics, self._subscriptions)
            if not subscription.get_publisher_count()
        ]
        sensors = [
            publisher.topic_name for publisher in [*self._odometry, *self._scans] if not publisher.get_subscription_count()
        ]
        return commands + sensors

    def _on_command(self, index: int, message: Twist) -> None:
        values = (message.linear.x, message.linear.y, message.linear.z, message.angular.x, message.angular.y)
        if not all(math.isfinite(value) for value in (*values, message.angular.z)):
            self.get_logger().warning(
                f"a command of agent {index} on {self._command_topics[index]} is not finite: taken as a zero command",
                throttle_duration_sec=1.0,
            )
            message = Twist()
        self._commands[index] = message
        self._received[index] += 1
        self._commanded[index] = True
        if self.settings.synchronous and self._episode >= 0 and not self.done and self._all_commanded():
            self._advance()

    def _all_commanded(self) -> bool:
        """Every agent that flies has sent a command since the last publication."""
        return bool(((self._received > 0) | self.failed).all())

    def _fail_silent_agents(self, waited: float) -> None:
        """Agents that commanded before and have been silent for ``waited`` s since the publication have failed:
        stop their motors, and step on if every other command is in."""
        silent = np.flatnonzero((self._received == 0) & self._commanded & ~self.failed).tolist()
        for agent in silent:
            try:
                self.env.engine.fail(self.env.team, agent)
            except ValueError as error:  # too few agents left to fly
                raise RuntimeError(f"agent {agent} sent no command for {waited:.1f} s and {error}") from None
            self.failed[agent] = True
            self.get_logger().warning(
                f"agent {agent} sent no command for {waited:.1f} s: its motors stop (failed) in episode {self._episode}"
            )
        if silent and self._all_commanded():
            self._advance()

    # Stepping -----------------------------------------------------------------------------------------------------

    def _start_episode(self) -> None:
        """Reset for the next episode (its seed), forget the commands, publish."""
        self._episode += 1
        self.env.reset(seed=self.settings.seed + self._episode)
        disturber = self.env.engine.disturber  # each agent's observation delay, drawn at the reset (none: ideal)
        delays = np.zeros(self.config.n_agents) if disturber is None else disturber.observation_delays[self._rows]
        self._deliveries.start(delays)
        self._episode_stamp = stamp_of(self._steps_played * self.config.dt)
        self._positions = [self.env.engine.latest.positions[self._rows].copy()]
        self._commands = [Twist() for _ in self._commands]
        self.failed[:] = False
        self._turn_rates[:] = 0.0
        self._publish()

    def _advance(self) -> None:
        """One step with each agent's latest command; record it; end the episode or publish."""
        if self.done:
            return
        actions = self._actions()
        _, _, terminated, truncated, _ = self.env.step_array(actions)
        self._steps_played += 1
        self._turn_rates = self.env.engine.model.turn_rates(actions)
        self._positions.append(self.env.engine.latest.positions[self._rows].copy())
        if not (terminated or truncated):
            self._publish()
            return
        steps = self.env.step_count
        self.results.append(EpisodeRecord(self.settings.seed + self._episode, terminated, steps, np.stack(self._positions)))
        self.get_logger().info(
            f"episode {self._episode} (seed {self.results[-1].seed}): success {terminated} in {steps} steps"
        )
        if len(self.results) < self.settings.episodes:
            self._start_episode()
        else:
            self.done = True
            for timer in self.timers:
                timer.cancel()

    def _actions(self) -> np.ndarray:
        """``(n, 2)`` the actions that give the agents' commands (:meth:`~sb3_formation.env.dynamics.DynamicsModel.action`),
        each read from the velocity, heading and forward speed its agent's odometry gave it (delivered: in the ideal
        world the truth of the last publication)."""
        model = self.env.engine.model
        told = [self._deliveries.delivered(i)[0] for i in range(self.config.n_agents)]
        velocities = np.array([team.velocities[i] for i, team in enumerate(told)])
        headings = np.array([team.headings[i] for i, team in enumerate(told)])
        speeds = np.array([team.forward_speeds[i] for i, team in enumerate(told)])
        actions = np.array(
            [
                model.action(twist_command(message, model, float(headings[i])), velocities[i], float(speeds[i]))
                for i, message in enumerate(self._commands)
            ]
        )
        for i in np.flatnonzero(~np.isfinite(actions).all(axis=1)):  # a command too large for its action (overflow)
            self.get_logger().warning(f"the command of agent {i} gives no finite action: taken as a zero command")
            zero = twist_command(Twist(), model, float(headings[i]))
            actions[i] = model.action(zero, velocities[i], float(speeds[i]))
        return actions

    def _publish(self) -> None:
        """The clock, the goal, every odometry, then every scan, all of the step's sim time (the goal of its
        episode's start: an agent sees a new episode's goal before its first scan; an agent's scan of its observation
        delay before, with that step's stamp); the sync mode's count of commands starts afresh."""
        config, engine, settings = self.config, self.env.engine, self.settings
        stamp = stamp_of(self._steps_played * config.dt)
        team = published_team(engine, self.env.team, stopped_by_agents=not settings.see_through_agents)
        reach = (config.agent_radius, config.agent_radius + config.lidar_range)
        scans = [  # beam k along world angle 2 pi k / n_rays, as the agent reads it (turned by its heading error)
            scan_message(stamp, self._frames[i], team.ranges[i], float(team.scan_angles[i]), *reach)
            for i in range(config.n_agents)
        ]
        self._deliveries.add((team, scans))
        self._received[:] = 0
        self._published_at = time.monotonic()
        self._clock.publish(ClockMessage(clock=stamp))
        self._goal.publish(goal_message(self._episode_stamp, settings.world_frame, engine.episodes.goals[self.env.team]))
        for i, publisher in enumerate(self._odometry):
            frames = (settings.world_frame, self._frames[i])
            odometry = (team.positions[i], float(team.headings[i]), team.body_velocities[i], self._turn_rates[i])
            publisher.publish(odometry_message(stamp, frames, *odometry))
        for i, publisher in enumerate(self._scans):
            publisher.publish(self._deliveries.delivered(i)[1][i])

    # Results ------------------------------------------------------------------------------------------------------

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write :attr:`results` to an ``.npz`` file: arrays ``seed``, ``success``, ``steps`` and ``positions_{k}`` of
        episode k (``(steps + 1, n, 2)`` m).

        :raises ValueError: another suffix
        """
        path = Path(path)
        if path.suffix != ".npz":
            raise ValueError(f"the episodes are saved as an .npz file, got {str(path)!r}")
        records = self.results
        arrays = {
            "seed": np.array([record.seed for record in records], dtype=np.int64),
            "success": np.array([record.success for record in records], dtype=bool),
            "steps": np.array([record.steps for record in records], dtype=np.int64),
            **{f"positions_{k}": record.positions for k, record in enumerate(records)},
        }
        with atomic_path(path) as temporary, open(temporary, "wb") as stream:
            np.savez(stream, **cast("dict[str, Any]", arrays))  # numpy's stubs read the keys as options
