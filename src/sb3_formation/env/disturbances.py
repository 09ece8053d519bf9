"""Disturbances as data: the errors of a real robot's sensors, motors, timing and radio, one typed section of the task
(:attr:`~sb3_formation.env.config.FormationConfig.disturbances`).

Five parts, each a frozen dataclass whose fields have units and a default of no error:

- :class:`Sensing`: lidar range noise and dropped beams; the error of every agent's estimate of its own position,
  heading and velocity (a white part and a slowly drifting bias). Neighbours know each other through what each
  broadcasts, so what an agent knows of its neighbours carries their own estimates' errors;
- :class:`Acting`: a motor gain per robot, drawn once per episode; force noise each step; a unicycle's turn-rate gain
  (wheel slip);
- :class:`Timing`: observation and action delays per robot, drawn once per episode, and jitter per step; an action
  delay may be a part of a step, for which the previous action holds;
- :class:`Communication`: for policies whose agents send messages, the loss of a message on each link and an extra
  delay; a lost message is received as the last one heard on that link;
- :class:`Failures`: an agent whose motors stop at a random step; the others re-form without it.

:data:`PROFILES` names the shipped ones: ``ideal`` (the default: no disturbance, the env unchanged bit for bit),
``realistic``, ``harsh`` and ``failures``, files in ``disturbance_profiles/`` beside this module whose comments give
the source of each number. :func:`load_disturbances` reads a profile's name or any file of the same format.
:meth:`Disturbances.scaled` multiplies every error by a level (0: ideal, 1: the profile, 2: twice it), the robustness
curves' axis; with ``randomise`` each episode draws its level between 0 and 1 (domain randomisation, for training).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, TypeVar

from sb3_formation.utils.checks import is_number
from sb3_formation.utils.yaml_files import read_yaml_file

#: The folder of the shipped profiles (``<name>.yaml``).
PROFILES_FOLDER = Path(__file__).with_name("disturbance_profiles")
#: The shipped profiles: ``ideal`` (the default, without a file: every field at its default), the signals' errors
#: mildest first, then ``failures`` (agents that fail in an ideal world).
PROFILES: tuple[str, ...] = ("ideal", "realistic", "harsh", "failures")
#: The parts of a :class:`Disturbances`, as they are named in a file and by the robustness curves' factors.
PARTS: tuple[str, ...] = ("sensing", "acting", "timing", "communication", "failures")
#: The longest delay (steps) of an observation, an action or a message: 100 times the harsh profile's.
MAX_DELAY_STEPS = 200
#: The latest step (steps) at which an agent may fail: far beyond any episode's T_s.
MAX_EPISODE_STEPS = 100_000
#: The longest drift correlation time (s): a day.
MAX_DRIFT_TIME = 86_400.0

PartT = TypeVar("PartT", bound="_Part")


@dataclass(frozen=True)
class _Part:
    """Base of the parts: validation by kind of field, scaling by a level, reading a mapping."""

    #: the part's name in a file
    key: ClassVar[str]
    #: fields that are probabilities (scaled, then capped at 1)
    probabilities: ClassVar[tuple[str, ...]] = ()
    #: fields that are gain intervals ``(low, high)`` around 1 (scaled away from 1)
    gains: ClassVar[tuple[str, ...]] = ()
    #: fields that are intervals ``(low, high)`` of delays in steps (scaled; whole steps where :attr:`whole` says so)
    intervals: ClassVar[tuple[str, ...]] = ()
    #: interval fields whose values are whole steps
    whole: ClassVar[tuple[str, ...]] = ()
    #: fields kept as they are by scaling (time constants)
    fixed: ClassVar[tuple[str, ...]] = ()
    #: interval fields kept as they are by scaling (when something happens, not how much)
    kept: ClassVar[tuple[str, ...]] = ()

    def __post_init__(self) -> None:
        for item in dataclasses.fields(self):
            name, value = item.name, getattr(self, item.name)
            if name in self.gains or name in self.intervals:
                self._check_interval(name, value)
            elif name in self.probabilities:
                self._require(name, value, "a probability in [0, 1]", is_number(value) and 0 <= value <= 1)
            elif name in self.fixed:
                valid = is_number(value) and 0 < value <= MAX_DRIFT_TIME
                self._require(name, value, f"a number > 0 and <= {MAX_DRIFT_TIME:g}", valid)
            else:
                self._require(name, value, "a finite number >= 0", is_number(value) and value >= 0)
            if not (name in self.gains or name in self.intervals):
                object.__setattr__(self, name, float(value))

    def _check_interval(self, name: str, value: Any) -> None:
        pair = isinstance(value, (tuple, list)) and len(value) == 2 and all(is_number(v) for v in value)
        self._require(name, value, "a pair [low, high] of finite numbers", pair)
        low, high = (float(v) for v in value)
        if name in self.gains:
            self._require(name, value, "a pair [low, high] with 0 < low <= 1 <= high", 0 < low <= 1 <= high)
        else:
            most = MAX_EPISODE_STEPS if name in self.kept else MAX_DELAY_STEPS
            valid = 0 <= low <= high <= most
            self._require(name, value, f"a pair [low, high] of steps with 0 <= low <= high <= {most}", valid)
            if name in self.whole:
                self._require(name, value, "whole steps", float(low).is_integer() and float(high).is_integer())
                low, high = int(low), int(high)
        object.__setattr__(self, name, (low, high))

    def _require(self, name: str, value: Any, allowed: str, valid: bool) -> None:
        if not valid:
            raise ValueError(f"disturbances: {self.key}.{name}={value!r} is invalid: it must be {allowed}")

    @property
    def is_ideal(self: PartT) -> bool:
        """No error at all (time constants aside)."""
        return self.scaled(0.0) == self

    def scaled(self: PartT, level: float) -> PartT:
        """Every error multiplied by ``level`` (>= 0): standard deviations and delays times it, probabilities times it
        (at most 1), gain intervals stretched away from 1 (a gain g becomes 1 + level (g - 1), at least 0.01); whole
        steps rounded to the nearest (a half up); time constants kept."""
        changes: dict[str, Any] = {}
        for item in dataclasses.fields(self):
            name, value = item.name, getattr(self, item.name)
            if name in self.fixed or name in self.kept:
                continue
            if name in self.gains:
                changes[name] = tuple(max(0.01, 1.0 + level * (v - 1.0)) for v in value)
                changes[name] = (min(changes[name][0], 1.0), max(changes[name][1], 1.0))
            elif name in self.intervals:
                stretched = tuple(min(level * v, MAX_DELAY_STEPS) for v in value)
                changes[name] = tuple(float(math.floor(v + 0.5)) for v in stretched) if name in self.whole else stretched
            elif name in self.probabilities:
                changes[name] = min(1.0, level * value)
            else:
                changes[name] = level * value
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_dict(cls: type[PartT], values: Any, base: PartT | None = None) -> PartT:
        """The part from a file's mapping of field values, the others from ``base`` (default: no error).

        :raises ValueError: not a mapping, or unknown fields (the valid ones are listed)
        """
        if not isinstance(values, Mapping):
            raise ValueError(f"disturbances: {cls.key} must be a mapping of its fields, got {type(values).__name__}")
        names = [item.name for item in dataclasses.fields(cls)]
        unknown = sorted(set(values) - set(names))
        if unknown:
            raise ValueError(f"disturbances: unknown {cls.key} field(s) {unknown}; valid: {names}")
        start = base if base is not None else cls()
        return dataclasses.replace(start, **dict(values))

    def to_dict(self) -> dict[str, Any]:
        """The fields as plain YAML data (pairs as lists)."""
        return {name: list(value) if isinstance(value, tuple) else value for name, value in dataclasses.asdict(self).items()}


@dataclass(frozen=True)
class Sensing(_Part):
    """What an agent's sensors get wrong (noise on the underlying estimates; the observation of Table 3.1 is derived
    from them, so its distances, angles and errors stay consistent with each other).

    :param lidar_noise: standard deviation (m) of the Gaussian error of every range a beam returns (a beam that sees
        nothing stays at the range); noisy ranges are clipped to [0, range]
    :param beam_dropout: probability that a beam returns nothing (reads 1, nothing seen), per beam and step
    :param position_noise: standard deviation (m), per axis, of the white error of an agent's position estimate
    :param position_drift: stationary standard deviation (m), per axis, of the drifting bias of that estimate
    :param heading_noise_deg: standard deviation (deg) of the white error of an agent's heading estimate: it turns the
        frame in which the agent reads its lidar and its velocity (and a unicycle's observed heading)
    :param heading_drift_deg: stationary standard deviation (deg) of the drifting bias of that estimate
    :param velocity_noise: standard deviation (m/s), per axis, of the white error of an agent's velocity estimate
    :param drift_time: correlation time (s) of the drifting biases: each is a first-order Gauss-Markov process, its
        correlation over a step exp(-dt / drift_time)
    """

    key: ClassVar[str] = "sensing"
    probabilities: ClassVar[tuple[str, ...]] = ("beam_dropout",)
    fixed: ClassVar[tuple[str, ...]] = ("drift_time",)

    lidar_noise: float = 0.0
    beam_dropout: float = 0.0
    position_noise: float = 0.0
    position_drift: float = 0.0
    heading_noise_deg: float = 0.0
    heading_drift_deg: float = 0.0
    velocity_noise: float = 0.0
    drift_time: float = 30.0

    @property
    def localises(self) -> bool:
        """Some error of the agents' position, heading or velocity estimates."""
        errors = (self.position_noise, self.position_drift, self.heading_noise_deg, self.heading_drift_deg)
        return any(errors) or bool(self.velocity_noise)


@dataclass(frozen=True)
class Acting(_Part):
    """What a robot's motors get wrong.

    :param gain: interval ``[low, high]`` of each robot's motor gain, drawn uniformly once per episode: the force (a
        unicycle's forward force) is the action's times the gain
    :param turn_gain: interval ``[low, high]`` of a unicycle's turn-rate gain (wheel slip), drawn like ``gain``
    :param force_noise: standard deviation, as a share of F_max per axis, of the Gaussian force added each step
        (a unicycle: to the forward force, and to the turn action as a share of its limit)
    """

    key: ClassVar[str] = "acting"
    gains: ClassVar[tuple[str, ...]] = ("gain", "turn_gain")

    gain: tuple[float, float] = (1.0, 1.0)
    turn_gain: tuple[float, float] = (1.0, 1.0)
    force_noise: float = 0.0


@dataclass(frozen=True)
class Timing(_Part):
    """When what a robot senses reaches its policy, and when what the policy decides reaches its motors.

    :param observation_delay: interval ``[low, high]`` of whole steps by which each robot's observations arrive late,
        drawn uniformly (an integer) once per episode: the policy acts on the observation of that many steps before
    :param action_delay: interval ``[low, high]`` of steps (any real) by which each robot's actions arrive late, drawn
        uniformly once per episode; until an action arrives the one before it holds (zero force before the first), so
        a delay of 0.4 applies the previous action for the first 40 % of the step
    :param jitter: each action's delay is the robot's plus a uniform draw from [0, jitter] steps; of actions that
        arrive out of order, the newest sent holds
    """

    key: ClassVar[str] = "timing"
    intervals: ClassVar[tuple[str, ...]] = ("observation_delay", "action_delay")
    whole: ClassVar[tuple[str, ...]] = ("observation_delay",)

    observation_delay: tuple[int, int] = (0, 0)
    action_delay: tuple[float, float] = (0.0, 0.0)
    jitter: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        self._require("jitter", self.jitter, f"at most {MAX_DELAY_STEPS} steps", self.jitter <= MAX_DELAY_STEPS)

    @property
    def longest_action_delay(self) -> float:
        """(steps) the longest delay an action can have."""
        return self.action_delay[1] + self.jitter


@dataclass(frozen=True)
class Communication(_Part):
    """What a radio gets wrong, for policies whose agents send messages.

    :param loss: probability that a message is lost on a link (each neighbour's copy apart), per step; the receiver
        then hears the last message that arrived on that link (zeros before the first)
    :param delay: interval ``[low, high]`` of whole steps added to the step a message always takes, drawn uniformly
        once per episode for each agent's links
    """

    key: ClassVar[str] = "communication"
    probabilities: ClassVar[tuple[str, ...]] = ("loss",)
    intervals: ClassVar[tuple[str, ...]] = ("delay",)
    whole: ClassVar[tuple[str, ...]] = ("delay",)

    loss: float = 0.0
    delay: tuple[int, int] = (0, 0)


@dataclass(frozen=True)
class Failures(_Part):
    """Agents that fail: at most one per team and episode, whose motors stop for good (``docs/disturbances.md``,
    "Agents that fail"). The failed agent stays where it stopped, a passive body that the others see as an obstacle;
    they close the ring without it and fly the formation of n - 1 (ring neighbours re-linked, the reference shape of
    n - 1), and success is judged on the agents that still fly.

    :param probability: probability that an agent of the team fails in an episode (which agent: uniform)
    :param steps: interval ``[low, high]`` of whole steps, the step of the failure drawn uniformly in it: the agent's
        motors stop at the end of that step (0: the episode starts with it failed); scaling keeps it
    """

    key: ClassVar[str] = "failures"
    probabilities: ClassVar[tuple[str, ...]] = ("probability",)
    intervals: ClassVar[tuple[str, ...]] = ("steps",)
    whole: ClassVar[tuple[str, ...]] = ("steps",)
    kept: ClassVar[tuple[str, ...]] = ("steps",)

    probability: float = 0.0
    steps: tuple[int, int] = (0, 0)


_PART_CLASSES: dict[str, type[_Part]] = {part.key: part for part in (Sensing, Acting, Timing, Communication, Failures)}


@dataclass(frozen=True)
class Disturbances:
    """The disturbances of a task (see the module docstring): every part's errors, and whether each episode draws its
    level.

    :param sensing: sensing noise (:class:`Sensing`)
    :param acting: actuator errors (:class:`Acting`)
    :param timing: delays (:class:`Timing`)
    :param communication: message loss and delay (:class:`Communication`)
    :param failures: agents whose motors stop (:class:`Failures`)
    :param randomise: each episode draws a level uniformly from [0, 1] and meets the disturbances scaled by it
        (:meth:`scaled`): domain randomisation between ``ideal`` and these
    """

    sensing: Sensing = Sensing()
    acting: Acting = Acting()
    timing: Timing = Timing()
    communication: Communication = Communication()
    failures: Failures = Failures()
    randomise: bool = False

    def __post_init__(self) -> None:
        for name, kind in _PART_CLASSES.items():
            if not isinstance(getattr(self, name), kind):
                raise ValueError(f"disturbances: {name} must be a {kind.__name__}, got {type(getattr(self, name)).__name__}")
        if not isinstance(self.randomise, bool):
            raise ValueError(f"disturbances: randomise={self.randomise!r} is invalid: it must be true or false")

    @property
    def is_ideal(self) -> bool:
        """No disturbance: the env is the ideal one, bit for bit."""
        return all(getattr(self, name).is_ideal for name in PARTS)

    @property
    def signals(self) -> Disturbances:
        """What disturbs the signals (every part but the failures): what the engine's disturber applies."""
        return dataclasses.replace(self, failures=Failures())

    def scaled(self, level: float) -> Disturbances:
        """Every part's errors times ``level`` (>= 0; :meth:`_Part.scaled`), randomise kept."""
        if not (is_number(level) and level >= 0):
            raise ValueError(f"a disturbance level must be a finite number >= 0, got {level!r}")
        return dataclasses.replace(self, **{name: getattr(self, name).scaled(float(level)) for name in PARTS})

    def only(self, part: str) -> Disturbances:
        """These disturbances' ``part`` alone (a name of :data:`PARTS`), the others ideal."""
        if part not in PARTS:
            raise ValueError(f"unknown part of the disturbances {part!r}; valid: {list(PARTS)}")
        return Disturbances(**{part: getattr(self, part)}, randomise=self.randomise)

    def randomised(self) -> Disturbances:
        """The same with ``randomise`` on."""
        return dataclasses.replace(self, randomise=True)

    @classmethod
    def from_dict(cls, values: Any, base: Disturbances | None = None) -> Disturbances:
        """Disturbances from a mapping as a file writes them: ``profile:`` (a name of :data:`PROFILES`, optional) to
        start from (else ``base``, else none), then any of the parts (each a mapping of its fields, the others from the
        profile) and ``randomise``.

        :raises ValueError: not a mapping, unknown keys or fields, invalid values (one line naming the field)
        """
        if isinstance(values, Disturbances):
            return values
        if not isinstance(values, Mapping):
            raise ValueError(f"disturbances must be a mapping (or a profile's name), got {type(values).__name__}")
        unknown = sorted(set(values) - {*PARTS, "randomise", "profile"})
        if unknown:
            raise ValueError(f"disturbances: unknown key(s) {unknown}; valid: {['profile', *PARTS, 'randomise']}")
        base = profile(values["profile"]) if "profile" in values else base or cls()
        changes: dict[str, Any] = {
            name: _PART_CLASSES[name].from_dict(values[name], getattr(base, name)) for name in PARTS if name in values
        }
        if "randomise" in values:
            changes["randomise"] = values["randomise"]
        return dataclasses.replace(base, **changes)

    def to_dict(self) -> dict[str, Any]:
        """Every part's fields as plain YAML data, and ``randomise``: what :meth:`from_dict` reads back."""
        return {**{name: getattr(self, name).to_dict() for name in PARTS}, "randomise": self.randomise}


def profile(name: Any) -> Disturbances:
    """A shipped profile by its name (:data:`PROFILES`).

    :raises ValueError: not a profile's name
    """
    if name not in PROFILES:
        raise ValueError(f"unknown disturbance profile {name!r}; valid: {list(PROFILES)}")
    if name == "ideal":
        return Disturbances()
    values = read_yaml_file(PROFILES_FOLDER / f"{name}.yaml")
    if isinstance(values, Mapping) and "profile" in values:
        raise ValueError(f"the shipped profile {name} must not start from another")
    return Disturbances.from_dict(values)


def load_disturbances(source: Any) -> Disturbances:
    """Disturbances from a profile's name (:data:`PROFILES`), a YAML file of :meth:`Disturbances.from_dict`'s format,
    or a mapping of that format (as a recipe or a config writes them).

    :raises ValueError: neither a profile's name nor a readable file of that format (one line naming it)
    """
    if isinstance(source, Disturbances):
        return source
    if isinstance(source, Mapping):
        return Disturbances.from_dict(source)
    if not isinstance(source, (str, Path)):
        raise ValueError(f"disturbances must be a profile's name, a file or a mapping, got {type(source).__name__}")
    if str(source) in PROFILES:
        return profile(str(source))
    path = Path(source)
    if not path.is_file():
        raise ValueError(f"disturbances {str(source)!r} are neither a profile ({', '.join(PROFILES)}) nor a file")
    values = read_yaml_file(path)
    try:
        return Disturbances.from_dict({} if values is None else values)
    except ValueError as error:
        raise ValueError(f"{path}: {error}") from None


def disturbance_label(source: str | Path) -> str:
    """The short name of disturbances given as a profile's name or a file (the file's stem), for folders and tables."""
    return str(source) if str(source) in PROFILES else Path(source).stem


def drift_correlation(drift_time: float, dt: float) -> float:
    """The correlation exp(-dt / drift_time) of a drifting bias over one step of ``dt`` seconds."""
    return math.exp(-dt / drift_time)
