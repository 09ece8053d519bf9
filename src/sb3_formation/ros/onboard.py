"""One robot's pipeline on board, without ROS: scan, team, goal and messages in; command, message and row out.

:class:`Onboard` is what the agent node (:mod:`~sb3_formation.ros.agent_node`, a thin rclpy shell that turns messages
into arrays and back) runs for every step it acts on, and what the latency benchmark and the tests call directly:

1. the scan resampled to the task's rays (:func:`~sb3_formation.ros.scans.resample_scan`) and split into the
   observation's two channels with the team's poses (:func:`~sb3_formation.ros.scans.split_scan`);
2. the observation row built from the team, the goal and the robot's memory
   (:class:`~sb3_formation.ros.observer.AgentObserver`);
3. the policy's agent step (:meth:`~sb3_formation.controllers.base.Policy.agent_step`: the action, the next state and
   the message to the ring neighbours), behind the safety filter when ``safety_filter`` is on
   (:func:`~sb3_formation.safety.policy.with_filter`: an export trained behind the filter keeps its own gains);
4. the action remembered for the next observation, and turned into the command the task's dynamics give it (eq. 19).

Numpy, the environment layer, the policy contract and the filter only: no rclpy.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from sb3_formation.controllers.base import TeamPolicy
from sb3_formation.env.dynamics import dynamics_model
from sb3_formation.env.geometry import ring_neighbours
from sb3_formation.ros.observer import FINAL_STAGE, AgentObserver, TeamView
from sb3_formation.ros.scans import Scan, ScanMount, resample_scan, split_scan
from sb3_formation.safety.policy import with_filter
from sb3_formation.utils.checks import is_count, is_integer, is_number


@dataclass(frozen=True)
class AgentSettings:
    """The agent node's settings and their defaults (each is also a ROS parameter of the node, same name).

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


class OnboardStep(NamedTuple):
    """What one step on board gives the robot."""

    command: np.ndarray  #: ``(2,)`` the command (:meth:`~sb3_formation.env.dynamics.DynamicsModel.command`)
    message: np.ndarray  #: ``(M,)`` float32 message to the ring neighbours (``(0,)`` if the agents send none)
    row: np.ndarray  #: ``(obs_dim,)`` float32 observation the policy acted on
    action: np.ndarray  #: ``(2,)`` float32 action taken (after the filter, if on)


class Onboard:
    """One robot's policy between its sensors and its command (see the module docstring).

    Call :meth:`reset` when a new goal arrives (an episode starts), then :meth:`step` for every step the robot acts on.

    :param policy: the policy (e.g. :func:`~sb3_formation.runtime.load_onnx_policy`'s); one may serve a whole team
    :param settings: the agent's settings (its index, scanner mount, scan tolerances, stage, filter on or off)
    :raises ValueError: an agent index outside the team, or a policy the observer cannot serve (a team reward)
    """

    def __init__(self, policy: TeamPolicy, settings: AgentSettings) -> None:
        self.settings = settings
        self.policy = with_filter(policy, settings.safety_filter)
        self.config = config = policy.config
        self.observer = AgentObserver(config, settings.agent, settings.stage)
        #: what the task's actions and commands mean
        self.dynamics = dynamics_model(config)
        self.mount = ScanMount(settings.scan_x, settings.scan_y, settings.scan_yaw)
        #: the ring neighbours (preceding, succeeding) whose messages the robot hears (none if its agents send none)
        ring = ring_neighbours(config.n_agents)[settings.agent]
        self.neighbours = tuple(int(index) for index in ring) if policy.message_size else ()
        self.reset()

    @property
    def message_size(self) -> int:
        """M, the values of each message (0: the agents send none)."""
        return self.policy.message_size

    def reset(self) -> None:
        """A new goal: forget the last episode (the observer's memory, the policy's state)."""
        self.observer.reset()
        self.state: Any = None
        #: no step taken yet in this episode
        self.starting = True

    def step(
        self, scan: Scan, team: TeamView, forward_speed: float, goal: np.ndarray, received: np.ndarray | None = None
    ) -> OnboardStep:
        """Observe, act (filtered, if on), remember and command, for one step.

        :param scan: the robot's scan
        :param team: every teammate's pose and velocity in the world frame (the robot's own among them)
        :param forward_speed: (m/s) the robot's forward speed (a unicycle's command needs it)
        :param goal: ``(2,)`` the goal (m)
        :param received: ``(2, M)`` what the preceding and succeeding neighbours sent at their last step (``None``:
            zeros, as at an episode's start)
        """
        config, settings, agent = self.config, self.settings, self.settings.agent
        readings = resample_scan(scan, self.mount, float(team.headings[agent]), config, settings.max_gap)
        lidar = split_scan(readings, config, team.positions, agent, settings.agent_tolerance)
        row = self.observer.observe(team, lidar, np.asarray(goal, dtype=np.float64)).astype(np.float32)[None, :]
        heard = None if received is None or not self.message_size else np.asarray(received)[None]
        start = np.array([self.starting])
        action, self.state, message = self.policy.agent_step(row, np.array([agent]), self.state, start, heard)
        self.starting = False
        self.observer.remember(action[0])
        command = self.dynamics.command(action[0], team.velocities[agent], forward_speed)
        return OnboardStep(command, message[0], row[0], action[0])
