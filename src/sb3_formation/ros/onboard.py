"""One robot's pipeline on board, without ROS: scan, team, goal and messages in; command, message and row out.

:class:`Onboard` is what the agent node (:mod:`~sb3_formation.ros.agent_node`, a thin rclpy shell that turns messages
into arrays and back) runs for every step it acts on, and what the latency benchmark and the tests call directly:

1. the scan resampled to the task's rays (:func:`~sb3_formation.ros.scans.resample_scan`) and split into the
   observation's two channels with the team's poses (:func:`~sb3_formation.ros.scans.split_scan`);
2. the observation row built from the team, the goal and the robot's memory
   (:class:`~sb3_formation.ros.observer.AgentObserver`);
3. the policy's agent step (:meth:`~sb3_formation.controllers.base.Policy.agent_step`: the action, the next state and
   the message to the ring neighbours), behind the safety filter when ``safety_filter`` is on
   (:func:`~sb3_formation.safety.policy.with_filter`: an export trained behind the filter keeps its own gains; the
   filter's bounds are those ``filter_disturbances`` declare, else the policy's task's);
4. the action remembered for the next observation, and turned into the command the task's dynamics give it (eq. 19).

Every input is checked before it reaches the policy (:meth:`Onboard.check`; ``docs/guarantees.md``, "On the robot"):
a scan of more than :data:`MAX_SCAN_RANGES` ranges or with angles or limits that place no return, a pose, velocity or
goal that is not finite or beyond :data:`MAX_COORDINATE` / :data:`MAX_SPEED`, a neighbour's message of the wrong size
or not finite, is an :class:`UnusableInput` (a one-line ``ValueError`` naming it), and so are a row, an action or a
command that came out non-finite. The node turns each into a zero command and a warning. The helpers the node uses
to judge its messages' stamps and its wall-clock silence (:func:`stamp_problem`, :class:`Silence`), the last check of
a command before it is published (:func:`command_problem`) and the reading of ROS parameters
(:func:`typed_parameters`) are here too, so that the node holds none of these rules.

Numpy, the environment layer, the policy contract and the filter only: no rclpy.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, fields
from typing import Any, NamedTuple

import numpy as np

from sb3_formation.controllers.base import TeamPolicy
from sb3_formation.env.disturbances import Disturbances, load_disturbances
from sb3_formation.env.dynamics import dynamics_model
from sb3_formation.ros.observer import FINAL_STAGE, AgentObserver, TeamView
from sb3_formation.ros.scans import Scan, ScanMount, resample_scan, split_scan
from sb3_formation.safety.filter import FilterBounds
from sb3_formation.safety.policy import SafePolicy, with_filter
from sb3_formation.utils.checks import is_count, is_integer, is_number, is_real

#: The most ranges a ``LaserScan`` may hold (a 0.05 deg scanner's 7200 fit): resampling costs rays x ranges, about
#: 0.06 s per scan of this size on one core, so a larger one is refused, before anything is allocated for it.
MAX_SCAN_RANGES = 8192
#: (m) The largest |x| or |y| of a pose or of the goal: ten times the largest world (``MAX_WORLD_SIZE``, 10 km).
MAX_COORDINATE = 1e5
#: (m/s) The largest speed an odometry may report (no robot of this kind moves faster).
MAX_SPEED = 100.0


class UnusableInput(ValueError):
    """An input the robot must not act on, in one line naming it; the node publishes a zero command instead."""


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
    :param input_timeout: (s) an input older than this (by its stamp and the node's clock), or not heard for this
        long on the wall clock, is stale: the robot stops
    :param failed_after: (s, wall clock) a teammate whose messages (every agent node sends one each step) have been
        silent this long in an episode has failed (synchronous mode: one without a message in 3 steps the robot acted
        on, which the simulator steps only once it failed it): the robot re-forms without it on the ring of the flying
        teammates (:meth:`Onboard.fail`) until the next goal, instead of waiting for it; 0: never (synchronous mode
        then waits for a talking policy's silent neighbour, and free mode stops on it)
    :param future_tolerance: (s) an input stamped further ahead of the node's clock than this is unusable (free mode)
    :param watchdog_rate: (Hz) how often stale inputs are looked for between scans (a wall-clock timer, in every mode)
    :param synchronous: act once per scan message, with every teammate's odometry of its stamp and a goal received
        since the last command (the simulator's synchronous mode: one command per step, deterministic); stamps are
        matched, not judged by the clock, and the watchdog stops the robot once nothing (inputs or ``clock_topic``) has
        been heard for ``input_timeout`` (a simulator that stopped)
    :param clock_topic: the simulator's clock, which it also publishes while it waits for commands: a sign of life that
        synchronous mode's watchdog listens to
    :param safety_filter: filter the actions (the policy's own gains if it was trained behind the filter, else the
        defaults)
    :param filter_disturbances: the errors the robot's filter stays safe under, declared by disturbances
        (:meth:`~sb3_formation.safety.filter.FilterBounds.declared`): a profile's name (``ideal``, ``realistic``,
        ``harsh``) or a YAML file (:func:`~sb3_formation.env.disturbances.load_disturbances`); ``""``: those of the
        policy's task (none for a policy of the ideal world)
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
    failed_after: float = 5.0
    future_tolerance: float = 0.5
    watchdog_rate: float = 10.0
    synchronous: bool = False
    safety_filter: bool = True
    stage: int = FINAL_STAGE
    qos_depth: int = 10
    best_effort_sensors: bool = False
    clock_topic: str = "/clock"
    filter_disturbances: str = ""

    def __post_init__(self) -> None:
        if self.filter_disturbances != "":
            check_disturbances("filter_disturbances", self.filter_disturbances)
        positive = ("max_gap", "input_timeout", "watchdog_rate")
        for name in positive:
            if not (is_number(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name} must be a number > 0, got {getattr(self, name)!r}")
        for name in ("agent_tolerance", "future_tolerance", "failed_after"):
            if not (is_number(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"{name} must be a number >= 0, got {getattr(self, name)!r}")
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
    A row belongs to its inputs' sensing time (``stamp``): inputs of the stamp the last row was built from (a delayed
    delivery that repeats them) give that row again, and the previous action a new row holds is the one taken at the
    step before its stamp's (:class:`~sb3_formation.ros.observer.AgentObserver`), as the engine's delayed rows hold
    them.

    :param policy: the policy (e.g. :func:`~sb3_formation.runtime.load_onnx_policy`'s); one may serve a whole team
    :param settings: the agent's settings (its index, scanner mount, scan tolerances, stage, filter on or off)
    :raises ValueError: an agent index outside the team, or a policy the observer cannot serve (a team reward)
    """

    def __init__(self, policy: TeamPolicy, settings: AgentSettings) -> None:
        self.settings = settings
        #: the errors the filter stays safe under (``None``: those of the policy's task)
        self.bounds = (
            FilterBounds.declared(load_disturbances(settings.filter_disturbances)) if settings.filter_disturbances else None
        )
        filtered = settings.safety_filter and self.bounds is not None
        self.policy = SafePolicy(policy, bounds=self.bounds) if filtered else with_filter(policy, settings.safety_filter)
        self.config = config = policy.config
        self.observer = AgentObserver(config, settings.agent, settings.stage)
        #: what the task's actions and commands mean
        self.dynamics = dynamics_model(config)
        self.mount = ScanMount(settings.scan_x, settings.scan_y, settings.scan_yaw)
        self.reset()

    @property
    def message_size(self) -> int:
        """M, the values of each message (0: the agents send none)."""
        return self.policy.message_size

    @property
    def neighbours(self) -> tuple[int, ...]:
        """The ring neighbours (preceding, succeeding) whose messages the robot hears, on the ring of the flying
        teammates (none if its agents send none)."""
        if not self.message_size:
            return ()
        return tuple(int(index) for index in self.observer.neighbours[self.settings.agent])

    @property
    def flying(self) -> np.ndarray:
        """``(n,)`` bool: the teammates that fly (:meth:`fail`)."""
        return self.observer.flying

    def fail(self, teammate: int) -> None:
        """A teammate failed (its node fell silent): the robot re-forms without it until the next goal, on the ring of
        the flying teammates (:meth:`~sb3_formation.ros.observer.AgentObserver.set_flying`); the policy acts at its
        place on that ring.

        :raises ValueError: the teammate is the robot itself or failed already, or fewer than 3 agents would fly
        """
        flying = self.flying.copy()
        if teammate == self.settings.agent or not 0 <= teammate < len(flying) or not flying[teammate]:
            raise ValueError(f"agent {self.settings.agent}: teammate {teammate} is not a flying teammate")
        flying[teammate] = False
        self.observer.set_flying(flying)

    def reset(self) -> None:
        """A new goal: forget the last episode (the observer's memory, the policy's state); every teammate flies."""
        self.observer.reset()
        self.state: Any = None
        #: no step taken yet in this episode
        self.starting = True
        self._stamp: int | None = None  # the sensing time of the last row, and that row
        self._row = np.zeros((1, self.observer.dim), dtype=np.float32)

    def _place(self) -> np.ndarray:
        """The robot's row of ``agents`` for the policy: its index, or its place and ring size once a teammate failed."""
        flying, agent = self.flying, self.settings.agent
        if flying.all():
            return np.array([agent])
        return np.array([[int(flying[:agent].sum()), int(flying.sum())]])

    def check(
        self, scan: Scan, team: TeamView, forward_speed: float, goal: np.ndarray, received: np.ndarray | None = None
    ) -> None:
        """Refuse inputs the robot must not act on (the arguments of :meth:`step`), before anything is computed of them.

        :raises UnusableInput: one line naming the input and what is wrong with it
        """
        problem = scan_problem(scan) or team_problem(team, self.config.n_agents)
        if not problem and not (is_real(forward_speed) and abs(forward_speed) <= MAX_SPEED):
            problem = f"the robot's forward speed {forward_speed!r} is not a number within {MAX_SPEED:g} m/s"
        if not problem:
            problem = _point_problem("the goal", goal)
        if not problem and received is not None and self.message_size:
            values = np.asarray(received)
            if values.shape != (2, self.message_size) or not np.isfinite(values).all():
                problem = f"the neighbours' messages are not 2 x {self.message_size} finite values"
        if problem:
            raise UnusableInput(problem)

    def step(
        self,
        scan: Scan,
        team: TeamView,
        forward_speed: float,
        goal: np.ndarray,
        received: np.ndarray | None = None,
        stamp: int | None = None,
    ) -> OnboardStep:
        """Check the inputs (:meth:`check`), observe, act (filtered, if on), remember and command, for one step.

        :param scan: the robot's scan
        :param team: every teammate's pose and velocity in the world frame (the robot's own among them)
        :param forward_speed: (m/s) the robot's forward speed (a unicycle's command needs it)
        :param goal: ``(2,)`` the goal (m)
        :param received: ``(2, M)`` what the preceding and succeeding neighbours sent at their last step (``None``:
            zeros, as at an episode's start)
        :param stamp: (ns) the inputs' sensing time: the stamp of the last row gives that row again (the same inputs,
            delivered again); ``None``: a new row
        :raises UnusableInput: an input the robot must not act on, or a row, action or command that came out
            non-finite; the robot's memory (observer, policy state) is then as before the call
        """
        self.check(scan, team, forward_speed, goal, received)
        config, settings, agent = self.config, self.settings, self.settings.agent
        memory = self.observer.memory()
        if stamp is not None and stamp == self._stamp:
            row = self._row
        else:
            readings = resample_scan(scan, self.mount, float(team.headings[agent]), config, settings.max_gap)
            lidar = split_scan(readings, config, team.positions, agent, settings.agent_tolerance, self.flying)
            row = self.observer.observe(team, lidar, np.asarray(goal, dtype=np.float64)).astype(np.float32)[None, :]
        if not np.isfinite(row).all():
            self.observer.restore(memory)
            raise UnusableInput("the observation row came out non-finite: not acted on")
        heard = None if received is None or not self.message_size else np.asarray(received)[None]
        start = np.array([self.starting])
        action, state, message = self.policy.agent_step(row, self._place(), self.state, start, heard)
        command = self.dynamics.command(action[0], team.velocities[agent], forward_speed)
        if not (np.isfinite(action).all() and np.isfinite(command).all() and np.isfinite(message).all()):
            self.observer.restore(memory)
            raise UnusableInput(f"the policy gave a non-finite action, command or message: {action[0].tolist()}")
        self.state, self.starting = state, False
        self._stamp, self._row = stamp, row
        self.observer.remember(action[0])
        return OnboardStep(command, message[0], row[0], action[0])


def check_disturbances(name: str, value: Any) -> Disturbances:
    """The disturbances a parameter ``name`` names (a profile's name or a YAML file,
    :func:`~sb3_formation.env.disturbances.load_disturbances`).

    :raises ValueError: neither, in one line naming the parameter
    """
    if not isinstance(value, str):
        raise ValueError(f"{name} must be a profile's name or a file, got {value!r}")
    try:
        return load_disturbances(value)
    except (ValueError, OSError) as error:
        raise ValueError(f"{name}: {error}") from None


def scan_problem(scan: Scan) -> str:
    """What makes a scan unusable, or ``""``: more than :data:`MAX_SCAN_RANGES` ranges (counted before anything is
    allocated) or none, angles that are not finite, limits that are NaN or admit no range (``range_min > range_max``).
    Ranges that are NaN, infinite or outside the limits are beams without a return (REP 117), not a fault."""
    problem = scan_size_problem(len(scan.ranges))
    if problem:
        return problem
    if not (math.isfinite(scan.angle_min) and math.isfinite(scan.angle_increment)):
        return f"the scan's angles are not finite (angle_min {scan.angle_min}, angle_increment {scan.angle_increment})"
    if not scan.range_min <= scan.range_max:  # NaN fails too
        return f"the scan's limits admit no range (range_min {scan.range_min}, range_max {scan.range_max})"
    return ""


def scan_size_problem(count: int) -> str:
    """What makes a scan of ``count`` ranges unusable (none, or more than :data:`MAX_SCAN_RANGES`), or ``""``."""
    if not 1 <= count <= MAX_SCAN_RANGES:
        return f"a scan of {count} ranges (1 to {MAX_SCAN_RANGES} are taken)"
    return ""


def team_problem(team: TeamView, n_agents: int) -> str:
    """What makes the team's poses and velocities unusable, naming the first teammate at fault, or ``""``: the wrong
    number of agents, a position beyond :data:`MAX_COORDINATE`, a velocity beyond :data:`MAX_SPEED`, a heading that is
    not finite (an orientation that is not a rotation, :func:`~sb3_formation.ros.messages.odometry_state`), or NaN."""
    positions, velocities = np.asarray(team.positions, dtype=np.float64), np.asarray(team.velocities, dtype=np.float64)
    headings = np.asarray(team.headings, dtype=np.float64)
    if positions.shape != (n_agents, 2) or velocities.shape != (n_agents, 2) or headings.shape != (n_agents,):
        return f"the team's poses are not those of {n_agents} agents"
    for index in range(n_agents):
        problem = _point_problem(f"agent {index}'s position", positions[index])
        if problem:
            return f"odometry of agent {index}: {problem}"
        if not (np.isfinite(velocities[index]).all() and np.abs(velocities[index]).max() <= MAX_SPEED):
            return f"odometry of agent {index}: velocity {velocities[index].tolist()} is not finite within {MAX_SPEED:g} m/s"
        if not math.isfinite(headings[index]):
            return f"odometry of agent {index}: its orientation is not a rotation (unit quaternion)"
    return ""


def _point_problem(what: str, point: np.ndarray) -> str:
    point = np.asarray(point, dtype=np.float64)
    if point.shape != (2,) or not (np.isfinite(point).all() and np.abs(point).max() <= MAX_COORDINATE):
        return f"{what} {point.tolist()} is not a finite point within {MAX_COORDINATE:g} m"
    return ""


def stamp_problem(what: str, stamp: int, now: int, settings: AgentSettings, judge_age: bool = True) -> str:
    """What makes an input's stamp unusable by the node's clock, or ``""``: older than ``input_timeout`` (when
    ``judge_age``: a latched goal's stamp is when it was given), or ahead of the clock by more than
    ``future_tolerance``.

    :param what: the input, for the message (its topic, say)
    :param stamp: (ns) the input's stamp
    :param now: (ns) the node's clock
    """
    age = (now - stamp) / 1e9
    if judge_age and age > settings.input_timeout:
        return f"{what} is {age:.3g} s old (input_timeout {settings.input_timeout:g} s)"
    if -age > settings.future_tolerance:
        return f"{what} is stamped {-age:.3g} s ahead of the clock (future_tolerance {settings.future_tolerance:g} s)"
    return ""


class Silence:
    """How long each input has not been heard, in wall-clock time the node could have heard it: a gap between two of
    the node's events (a callback, a watchdog tick) counts at most ``longest_gap`` s, so a node whose own work held
    its executor (a policy's first step compiling its kernels, say) does not take its inputs for stale when it wakes.
    Times are ``time.monotonic()`` seconds; a stopped ``/clock`` does not stop this.

    :param longest_gap: (s) the most one gap between events counts (a couple of watchdog periods)
    """

    def __init__(self, longest_gap: float) -> None:
        self.longest_gap = longest_gap
        #: (s) wall-clock time the node could hear, since it started
        self.listening = 0.0
        self._last: float | None = None
        self._heard: dict[str, float] = {}

    def tick(self, now: float) -> None:
        """An event of the node at wall-clock time ``now`` (s)."""
        if self._last is not None:
            self.listening += min(max(now - self._last, 0.0), self.longest_gap)
        self._last = now

    def heard(self, name: str, now: float) -> None:
        """Input ``name`` arrived at ``now`` (s)."""
        self.tick(now)
        self._heard[name] = self.listening

    def silent_for(self, name: str) -> float:
        """(s) since ``name`` was last heard (``inf``: never)."""
        return self.listening - self._heard[name] if name in self._heard else math.inf

    def ever_heard(self) -> bool:
        return bool(self._heard)


def command_problem(values: Iterable[float]) -> str:
    """The last check of a command (a ``Twist``'s six values) before it is published: ``""`` if every value is finite."""
    values = list(values)
    if all(math.isfinite(value) for value in values):
        return ""
    return f"refused to publish a non-finite command {values}"


def typed_parameters(defaults: Any, values: Mapping[str, Any]) -> dict[str, Any]:
    """ROS parameter values (``--ros-args -p name:=value``) as the types of a node's settings (a dataclass of
    defaults): an integer where a number (float) is declared is taken as that float (``-p input_timeout:=2``); any
    other type (``-p agent:=1.5``, ``-p input_timeout:=abc``) is a one-line ``ValueError`` naming the parameter.
    """
    typed = {}
    for item in fields(defaults):
        default, value = getattr(defaults, item.name), values[item.name]
        if isinstance(default, bool):
            kind, fits = "true or false", isinstance(value, bool)
        elif isinstance(default, int):
            kind, fits = "an integer", is_integer(value)
        elif isinstance(default, float):
            kind, fits = "a number", is_real(value)
            value = float(value) if fits else value
        else:
            kind, fits = "a string", isinstance(value, str)
        if not fits:
            raise ValueError(f"parameter {item.name} must be {kind}, got {value!r}")
        typed[item.name] = value
    return typed
