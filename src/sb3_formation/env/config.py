"""Every parameter of the formation task in one frozen dataclass, and the thesis's tasks.

Units are SI throughout: metres, seconds, kilograms, degrees only where the name says ``_deg``.
The four thesis tasks are data (:data:`TASKS`), not code branches: a new task is a new entry. (A *task* is what the
agents must do and how it is rewarded; a *recipe*, in the experiment layer, is how a policy is trained on a task.)
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Literal

from sb3_formation.env.disturbances import Disturbances, load_disturbances
from sb3_formation.env.geometry import interior_angle_deg
from sb3_formation.utils.checks import is_integer, is_number, is_real

#: Deepest overlap allowed between two agents, or an agent and an obstacle or a wall, as a fraction of the agent
#: radius (2 cm for the thesis's 20 cm agents). :attr:`FormationConfig.substeps_needed` keeps it.
OVERLAP_TOLERANCE = 0.1
#: Pymunk's contact bias: the fraction of an overlap left after one second of solving. Pymunk's default, (1 - 0.1)^60
#: as Chipmunk computes it (``pymunk.Space().collision_bias``); the world sets it explicitly.
COLLISION_BIAS = 0.0017970074436457143
#: The largest share of an overlap counted as removed by Pymunk in one step, however long: measured, crowds pressing
#: together keep more than the bias alone predicts for steps of 0.5 s.
MAX_OVERLAP_REMOVAL = 0.8
#: Pymunk sub-steps of the thesis's physics (the fewest the package uses).
THESIS_SUBSTEPS = 2
#: The most Pymunk sub-steps per environment step a configuration may need: 500 times the thesis's work per step, and
#: four times what the fastest, smallest agents of the fuzz-tested range need (v_max 1 m/s, dt 0.5 s, R_a 0.1 m: 125).
#: Beyond it one step takes seconds (v_max = 1e6 m/s would need 37.5 million).
MAX_SUBSTEPS = 1000
#: The largest world side (m): 1000 times the thesis's 10 m, far inside what float64 geometry keeps exact.
MAX_WORLD_SIZE = 10_000.0
#: The most lidar rays: a ray every 0.1 deg, 40 times the thesis's 90 (Table 4.1); each ray is two observation
#: features and a ray cast per agent and step, so 10^8 rays would take gigabytes per step.
MAX_LIDAR_RAYS = 3600
#: The most agents in a team: 8 times the largest team of the thesis's experiments (n = 8, chapter 5).
MAX_AGENTS = 64
#: The most steps of an episode, and the most placement draws: 40 times the scene families' 2,500 steps.
MAX_EPISODE_STEPS = 100_000

#: Names of the reward terms, in the order of eq. (42); chapter 4's ``ref`` term (eq. 22) is ``dist``.
REWARD_TERMS: tuple[str, ...] = ("time", "angle", "bearing", "dist", "centroid", "goal", "move", "velocity", "coll")
#: Keys of the reward terms in an agent's step infos, ``reward_<term>``: flat, so that every client library (TorchRL's
#: ``PettingZooWrapper`` stacks each info value as a tensor) takes them.
REWARD_INFO_KEYS: tuple[str, ...] = tuple(f"reward_{term}" for term in REWARD_TERMS)
#: Keys of an agent's step infos, in the order the env writes them (``FormationEnv``'s class docstring, "Info").
INFO_KEYS: tuple[str, ...] = (
    "angle_error_deg",
    "bearing_error",
    "neighbour_distance_error",
    "centroid_distance",
    "goal_distance",
    "collisions_obstacle",
    "collisions_agent",
    "collisions_rammed",
    "success",
    *REWARD_INFO_KEYS,
)

#: The thesis chapters whose curriculum placements the ``"curriculum"`` scenes draw (:attr:`FormationConfig.chapter`).
CHAPTERS: tuple[str, ...] = ("ch4", "ch5")
#: Agent dynamics (:attr:`FormationConfig.dynamics`): the thesis's holonomic point (eq. 19), or a unicycle.
DYNAMICS: tuple[str, ...] = ("holonomic", "unicycle")
#: What the goal term measures progress along (:attr:`FormationConfig.goal_progress`).
GOAL_PROGRESS: tuple[str, ...] = ("euclidean", "geodesic")


@dataclass(frozen=True)
class FormationConfig:
    """All parameters of one formation task. Validated on construction.

    :param world_width: width of the walled world (m), thesis 4.3 / 5.3
    :param world_height: height of the walled world (m)
    :param n_agents: number of agents n in the team (>= 3; with the thesis's eta_c and R_a at most 16 fit the start)
    :param agent_radius: agent radius R_a (m)
    :param agent_mass: agent mass m (kg)
    :param v_max: maximum agent speed (m/s); speeds are clamped to it
    :param max_force: force F_max (N) produced by an action of 1; ``None`` means m * v_max / dt,
        so a full action reaches v_max from rest in one step
    :param dynamics: ``"holonomic"`` (the thesis's, eq. 19: the action is a force (x, y) in the world frame) or
        ``"unicycle"`` (a differential-drive robot: state x, y, heading theta; the action is a forward force, a share
        of F_max along the heading, and a turn-rate command, a share of ``max_turn_rate``; no sideways motion; the
        forward speed is limited to [-v_max, v_max]; see :mod:`sb3_formation.env.world`). A unicycle's observation
        has its heading (cos, sin) after ``previous_reward`` (before any reference bearings), and its start faces the
        goal unless the scenario gives headings
    :param max_turn_rate: the unicycle's turn-rate limit (rad/s), reached by a turn action of 1; below pi per Pymunk
        sub-step (an arc's chord vanishes at a full turn)
    :param dt: environment step Delta t (s)
    :param physics_substeps: Pymunk sub-steps inside one environment step; ``None`` (default) becomes the fewest, and
        at least the thesis's 2, that keep overlaps within :data:`OVERLAP_TOLERANCE` (:attr:`substeps_needed`). A
        number given is refused if it lets bodies overlap more
    :param lidar_rays: number of lidar rays b x d, spread evenly over 360 deg starting at +x
    :param lidar_range: lidar range l_s (m), measured from the agent's surface
    :param d_ref: reference neighbour distance d^ref (m)
    :param d_comm: communication range d^comm (m)
    :param eta_c: centroid distance eta_c (m) (eq. 37; starting formation)
    :param eta_g: goal radius eta_g (m): the goal is reached when the centroid is this close
    :param max_steps: episode length T_s (steps): truncation, and r_late in chapter 5
    :param formation_scale: starting n-gon size as a fraction of the largest one allowed by d_ref and eta_c, in (0, 1)
    :param team_reward: every agent receives the team average (eqs 27-32) instead of its own reward
    :param k_time: coefficient of the time term (eq. 33; 1 in eq. 42)
    :param k_angle: K_angle, angle term (eq. 21 / 34)
    :param k_bearing: K_bearing, bearing term (eq. 35)
    :param k_dist: K_dist / K_ref, neighbour-distance term (eq. 22 / 36)
    :param k_centroid: coefficient of the centroid term (eq. 37; 1 in eq. 42)
    :param k_goal: K_goal, goal term (eq. 23 / 38)
    :param k_move: K_move, smoothness term (eq. 25 / 40)
    :param k_velocity: K_vel, velocity-alignment term (eq. 41)
    :param k_coll: K_coll, collision term (eq. 24 / 39)
    :param m_ang_deg: m_ang, angle-error scale (deg)
    :param m_dist: m_dist / m_ref, distance-error scale (m)
    :param r_c: centroid reward r_c
    :param r_reached: goal reward r_reached
    :param r_late: reward r_late at step T_s
    :param k1: constant k_1 of the goal term
    :param goal_progress: the distance whose decrease the goal term rewards (eqs. 23 / 38): ``"euclidean"`` (the
        thesis's, the straight centroid-goal distance c_g) or ``"geodesic"`` (a departure for scenes whose walls block
        the straight way: the length of the shortest way round the shapes, :func:`~sb3_formation.env.clearance.path_distance`).
        The goal is reached, and r_reached paid, within eta_g of c_g in both
    :param r_o: obstacle-collision reward r_o
    :param r_j: agent-collision reward r_j
    :param d_safe: safe gap d_safe (m) between an agent's surface and an obstacle's (walls included)
    :param reward_clip: per-agent rewards are clipped to [-reward_clip, reward_clip] after summing
    :param chapter: the thesis chapter whose curriculum placements the ``"curriculum"`` scenes draw: ``"ch4"``
        (thesis 4.3) or ``"ch5"`` (thesis 5.3)
    :param scenes: where episodes are placed: a name of the registry :data:`sb3_formation.env.scenes.SCENES`, checked
        when an engine is built: ``"curriculum"`` (the thesis's stages, by ``chapter``), a scene family
        (``"passage"``, ``"corridor"``, ``"trap"``, ``"clutter"``) or ``"mixed"`` (one family drawn per episode); the
        stage still chooses the reward terms
    :param stage: curriculum stage 1, 2 or 3
    :param stage_disabled_terms: for stages 1, 2, 3, the reward terms switched off in that stage
    :param max_placement_tries: scenario draws before the sampler gives up with an error
    :param placement_clearance: minimum gap (m) between a drawn obstacle and the start formation or the goal area
    :param observe_reference_bearings: append the agent's two reference bearings (Table 5.2, normalised) to its
        observation: a departure from Table 3.1 for policies that act in teams of several sizes, where an agent's
        reference depends on its index and n (the angle error already carries beta^ref)
    :param disturbances: the errors of real sensors, motors, timing and radios
        (:class:`~sb3_formation.env.disturbances.Disturbances`; a profile's name, a file or a mapping is read with
        :func:`~sb3_formation.env.disturbances.load_disturbances`); the default, ``ideal``, is none
    """

    world_width: float = 15.0
    world_height: float = 10.0
    n_agents: int = 6
    agent_radius: float = 0.2
    agent_mass: float = 1.0
    v_max: float = 0.05
    max_force: float | None = None
    dynamics: Literal["holonomic", "unicycle"] = "holonomic"
    max_turn_rate: float = 0.5
    dt: float = 0.3
    physics_substeps: int | None = None
    lidar_rays: int = 90
    lidar_range: float = 1.5
    d_ref: float = 1.5
    d_comm: float = 3.0
    eta_c: float = 1.2
    eta_g: float = 0.4
    max_steps: int = 2500
    formation_scale: float = 0.9
    team_reward: bool = False
    k_time: float = 1.0
    k_angle: float = 0.0
    k_bearing: float = 0.3
    k_dist: float = 1.0
    k_centroid: float = 1.0
    k_goal: float = 0.5
    k_move: float = 0.3
    k_velocity: float = 0.1
    k_coll: float = 0.5
    m_ang_deg: float = 30.0
    m_dist: float = 0.1
    r_c: float = 0.01
    r_reached: float = 4.0
    r_late: float = -10.0
    k1: float = -1.1
    goal_progress: Literal["euclidean", "geodesic"] = "euclidean"
    r_o: float = -5.0
    r_j: float = -1.0
    d_safe: float = 0.05
    reward_clip: float = 10.0
    chapter: Literal["ch4", "ch5"] = "ch5"
    scenes: str = "curriculum"
    stage: int = 1
    stage_disabled_terms: tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]] = (
        ("dist", "angle", "bearing"),
        ("angle", "bearing"),
        (),
    )
    max_placement_tries: int = 200
    placement_clearance: float = 0.05
    observe_reference_bearings: bool = False
    disturbances: Disturbances = dataclasses.field(default_factory=Disturbances)

    def __post_init__(self) -> None:
        object.__setattr__(self, "disturbances", load_disturbances(self.disturbances))
        positive = (
            "world_width world_height agent_radius agent_mass v_max max_turn_rate dt lidar_range d_ref d_comm eta_c "
            "eta_g m_ang_deg m_dist reward_clip"
        ).split()
        for name in positive:
            _check(name, getattr(self, name), "a finite number > 0", lambda v: is_number(v) and v > 0)
        for name in ("world_width", "world_height"):
            _check(name, getattr(self, name), f"at most {MAX_WORLD_SIZE:g} m", lambda v: v <= MAX_WORLD_SIZE)
        for name in "r_c r_reached r_late k1 r_o r_j".split() + [f"k_{t}" for t in REWARD_TERMS]:
            _check(name, getattr(self, name), "a finite number", lambda v: is_number(v))
        _check("d_safe", self.d_safe, "a finite number >= 0", lambda v: is_number(v) and v >= 0)
        clearance = self.placement_clearance
        _check("placement_clearance", clearance, "a number >= 0", lambda v: is_number(v) and v >= 0)
        force = self.max_force
        _check("max_force", force, "None or a number > 0", lambda v: v is None or (is_number(v) and v > 0))
        limits = {"n_agents": (3, MAX_AGENTS), "lidar_rays": (1, MAX_LIDAR_RAYS), "max_steps": (1, MAX_EPISODE_STEPS)}
        for name, (least, most) in {**limits, "max_placement_tries": (1, MAX_EPISODE_STEPS)}.items():
            in_range = f"an integer >= {least} and <= {most}"
            _check(name, getattr(self, name), in_range, lambda v: is_integer(v) and least <= v <= most)  # noqa: B023
        substeps = self.physics_substeps
        _check("physics_substeps", substeps, "None or an integer >= 1", lambda v: v is None or (is_integer(v) and v >= 1))
        _check("stage", self.stage, "1, 2 or 3", lambda v: is_integer(v) and v in (1, 2, 3))
        for name in ("n_agents", "lidar_rays", "max_steps", "max_placement_tries", "stage"):
            object.__setattr__(self, name, int(getattr(self, name)))  # numpy integers become plain ints
        if self.substeps_needed > MAX_SUBSTEPS:
            raise ValueError(
                f"v_max={self.v_max:g} m/s, dt={self.dt:g} s and agent_radius={self.agent_radius:g} m need "
                f"{self.substeps_needed:,} Pymunk sub-steps per step to keep overlaps within {OVERLAP_TOLERANCE:.0%} of "
                f"agent_radius, above the maximum of {MAX_SUBSTEPS}: lower v_max or dt, or raise agent_radius"
            )
        _check("physics_substeps", substeps, f"at most {MAX_SUBSTEPS}", lambda v: v is None or v <= MAX_SUBSTEPS)
        object.__setattr__(self, "physics_substeps", self.substeps_needed if substeps is None else int(substeps))
        _check("formation_scale", self.formation_scale, "in (0, 1)", lambda v: is_real(v) and 0 < v < 1)
        _check("chapter", self.chapter, f"one of {CHAPTERS}", lambda v: v in CHAPTERS)
        _check("dynamics", self.dynamics, f"one of {DYNAMICS}", lambda v: v in DYNAMICS)
        _check("goal_progress", self.goal_progress, f"one of {GOAL_PROGRESS}", lambda v: v in GOAL_PROGRESS)
        _check("scenes", self.scenes, "a name of sb3_formation.env.scenes.SCENES", lambda v: isinstance(v, str) and v != "")
        for name in ("team_reward", "observe_reference_bearings"):
            _check(name, getattr(self, name), "True or False", lambda v: isinstance(v, bool))
        if self.d_comm <= self.d_ref:
            raise ValueError(f"d_comm={self.d_comm} must be > d_ref={self.d_ref}")
        disabled = tuple(tuple(stage_terms) for stage_terms in self.stage_disabled_terms)
        if len(disabled) != 3:
            raise ValueError(f"stage_disabled_terms must list the disabled terms of stages 1, 2 and 3, got {disabled!r}")
        for stage_terms in disabled:
            unknown = sorted(set(stage_terms) - set(REWARD_TERMS))
            if unknown:
                raise ValueError(f"stage_disabled_terms names unknown reward terms {unknown}; valid: {list(REWARD_TERMS)}")
        object.__setattr__(self, "stage_disabled_terms", disabled)
        assert self.physics_substeps is not None  # an int from here on: set from substeps above
        if self.physics_substeps < self.substeps_needed:
            raise ValueError(
                f"physics_substeps={self.physics_substeps} lets agents move {self.v_max * self.dt / self.physics_substeps:.4f}"
                f" m per Pymunk sub-step, more than the {self.max_substep_travel:.4f} m that keeps overlaps within "
                f"{OVERLAP_TOLERANCE:.0%} of agent_radius: give physics_substeps >= {self.substeps_needed}, or leave it "
                "unset (chosen from v_max, dt and agent_radius)"
            )
        turn_gain = self.disturbances.acting.turn_gain[1] if self.dynamics == "unicycle" else 1.0
        if self.max_turn_rate * turn_gain * self.dt / self.physics_substeps >= math.pi:
            raise ValueError(
                f"max_turn_rate={self.max_turn_rate:g} rad/s (times the largest turn gain {turn_gain:g}) turns a unicycle "
                f"by pi or more in one of the {self.physics_substeps} Pymunk sub-steps of dt={self.dt:g} s: lower it below "
                f"{math.pi * self.physics_substeps / self.dt / turn_gain:.4g} rad/s"
            )
        side = self.start_side_length
        if side <= 2 * self.agent_radius:
            raise ValueError(
                f"n_agents={self.n_agents} does not fit the starting formation: its side {side:.3f} m "
                f"(from d_ref, eta_c, formation_scale) is below the agent diameter {2 * self.agent_radius:.3f} m; "
                "with the thesis's sizes at most 16 agents fit within eta_c, so raise eta_c or lower agent_radius"
            )
        extent = 2 * (self.start_circumradius + self.agent_radius)
        if extent >= min(self.world_width, self.world_height):
            raise ValueError(f"the starting formation ({extent:.2f} m across) does not fit the world")

    # Derived values -------------------------------------------------------------------------------------------

    @property
    def force_max(self) -> float:
        """F_max (N): the force of a unit action; m * v_max / dt unless ``max_force`` is set."""
        return self.max_force if self.max_force is not None else self.agent_mass * self.v_max / self.dt

    @property
    def max_substep_travel(self) -> float:
        """The longest move (m) of an agent in one Pymunk sub-step that keeps overlaps within
        :data:`OVERLAP_TOLERANCE`: two agents closing head-on (2 v_max) sink by up to twice one agent's move per
        sub-step before the solver stops them, and over a step Pymunk removes the share 1 - bias^dt of an overlap
        (:data:`COLLISION_BIAS`), taken as at most :data:`MAX_OVERLAP_REMOVAL`; the move keeps this balance within the
        tolerance (checked for 3-16 agents, radii 0.1-0.3 m, v_max 0.05-1 m/s, dt 0.05-0.5 s by the fuzz test)."""
        removal: float = min(1.0 - COLLISION_BIAS**self.dt, MAX_OVERLAP_REMOVAL)  # float ** float is typed Any
        return OVERLAP_TOLERANCE * self.agent_radius * removal / 2.0

    @property
    def substeps_needed(self) -> int:
        """The fewest Pymunk sub-steps per environment step whose moves stay within :attr:`max_substep_travel`, and
        at least the thesis's 2."""
        return max(THESIS_SUBSTEPS, math.ceil(self.v_max * self.dt / self.max_substep_travel))

    @property
    def beta_ref_deg(self) -> float:
        """Reference angle beta^ref (deg): the interior angle (n - 2) * 180 / n of the regular n-gon (Tables 4.1, 5.1)."""
        return interior_angle_deg(self.n_agents)

    @property
    def start_circumradius(self) -> float:
        """Circumradius (m) of the starting n-gon: every side below d_ref, every agent within eta_c of the centroid."""
        largest = min(self.eta_c, self.d_ref / (2.0 * math.sin(math.pi / self.n_agents)))
        return self.formation_scale * largest

    @property
    def start_side_length(self) -> float:
        """Side (m) of the starting n-gon."""
        return 2.0 * self.start_circumradius * math.sin(math.pi / self.n_agents)

    @property
    def world_diagonal(self) -> float:
        """Length (m) of the world's diagonal: the largest distance between two points in it."""
        return math.hypot(self.world_width, self.world_height)

    def reward_coefficients(self, stage: int | None = None) -> dict[str, float]:
        """Coefficient of every reward term in ``stage`` (default: ``self.stage``), with the stage's disabled terms at 0."""
        stage = self.stage if stage is None else stage
        _check_stage(stage)
        disabled = self.stage_disabled_terms[stage - 1]
        return {term: 0.0 if term in disabled else float(getattr(self, f"k_{term}")) for term in REWARD_TERMS}

    # Construction ---------------------------------------------------------------------------------------------

    @classmethod
    def field_names(cls) -> tuple[str, ...]:
        """Names of every field, for overrides and YAML files."""
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def task(cls, name: str, **overrides: Any) -> FormationConfig:
        """The configuration of the thesis task ``name`` (see :data:`TASKS`), with ``overrides`` applied.

        :param name: ``"ch4-individual"``, ``"ch4-team"``, ``"ch5-angle"`` or ``"ch5-bearing"``
        :param overrides: field values replacing the task's
        """
        if name not in TASKS:
            raise ValueError(f"unknown task {name!r}; valid tasks: {sorted(TASKS)}")
        unknown = sorted(set(overrides) - set(cls.field_names()))
        if unknown:
            raise ValueError(f"unknown FormationConfig field(s) {unknown}; valid fields: {list(cls.field_names())}")
        return cls(**{**TASKS[name], **overrides})

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> FormationConfig:
        """A configuration from the mapping :meth:`to_dict` writes (lists where fields hold tuples).

        :raises ValueError: not a mapping, or unknown fields (the valid ones are listed)
        """
        if not isinstance(values, dict):
            raise ValueError(f"a FormationConfig is a mapping of field names to values, not {type(values).__name__}")
        unknown = sorted(set(values) - set(cls.field_names()))
        if unknown:
            raise ValueError(f"unknown FormationConfig field(s) {unknown}; valid fields: {list(cls.field_names())}")
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        """Every field as plain YAML/JSON data: the one way a configuration is written (run folders, model files,
        trajectories). Sub-steps chosen from v_max, dt and agent_radius are written as ``None``, so that they are
        chosen again when read (and when another field is overridden); ideal disturbances are not written."""
        values = dataclasses.asdict(self)
        values["stage_disabled_terms"] = [list(terms) for terms in self.stage_disabled_terms]
        if self.disturbances.is_ideal:  # the ideal world's configuration reads as it always did
            del values["disturbances"]
        else:
            values["disturbances"] = self.disturbances.to_dict()
        if self.physics_substeps == self.substeps_needed:
            values["physics_substeps"] = None
        return values

    def replace(self, **changes: Any) -> FormationConfig:
        """A copy with ``changes`` applied (validated like a new config). Sub-steps that were chosen for this config
        (``physics_substeps`` equal to :attr:`substeps_needed`) are chosen again for the copy unless given."""
        unknown = sorted(set(changes) - set(self.field_names()))
        if unknown:
            raise ValueError(f"unknown FormationConfig field(s) {unknown}; valid fields: {list(self.field_names())}")
        if "physics_substeps" not in changes and self.physics_substeps == self.substeps_needed:
            changes["physics_substeps"] = None
        return dataclasses.replace(self, **changes)


def _check_stage(stage: Any) -> None:
    if not (is_integer(stage) and stage in (1, 2, 3)):
        raise ValueError(f"stage must be 1, 2 or 3, got {stage!r}")


def _check(name: str, value: Any, allowed: str, ok: Any) -> None:
    try:
        valid = bool(ok(value))
    except TypeError:
        valid = False
    if not valid:
        raise ValueError(f"FormationConfig.{name}={value!r} is invalid: it must be {allowed}")


# Thesis tasks --------------------------------------------------------------------------------------------------

#: Chapter 4 (angle reward, n = 3): Table 4.1. Chapter 4 uses but does not list k_1, eta_c, r_c and r_late;
#: they come from Table 5.1 (k_1 = -1.1, eta_c = 1.2 m; r_c and r_late are inactive since eq. 26 has no
#: centroid or time term, so k_centroid = k_time = 0). K_ref of eq. (26) is ``k_dist``, m_ref is ``m_dist``.
_CH4: dict[str, Any] = {
    "n_agents": 3,
    "k_goal": 0.5,  # Table 4.1
    "k_dist": 2.0,  # Table 4.1, K_ref
    "k_angle": 0.4,  # Table 4.1
    "k_move": 2.0,  # Table 4.1
    "k_coll": 1.0,  # Table 4.1
    "k_bearing": 0.0,  # eq. 26 has no bearing term
    "k_velocity": 0.0,  # eq. 26 has no velocity term
    "k_centroid": 0.0,  # eq. 26 has no centroid term
    "k_time": 0.0,  # eq. 26 has no time term
    "r_reached": 9.0,  # Table 4.1
    "eta_g": 0.5,  # Table 4.1
    "m_ang_deg": 30.0,  # Table 4.1; beta^f = 60 deg is the interior angle for n = 3 (beta_ref_deg)
    "d_ref": 2.4,  # Table 4.1
    "d_comm": 3.0,  # Table 4.1
    "m_dist": 0.1,  # Table 4.1, m^ref
    "r_o": -6.0,  # Table 4.1
    "r_j": -1.0,  # Table 4.1
    "d_safe": 0.02,  # Table 4.1
    "k1": -1.1,  # Table 5.1 (not listed in Table 4.1)
    "eta_c": 1.2,  # Table 5.1 (starting formation)
    "r_c": 0.01,  # Table 5.1 (inactive)
    "r_late": -10.0,  # Table 5.1 (inactive)
    "chapter": "ch4",  # thesis 4.3
    "stage_disabled_terms": (("angle",), (), ()),  # phase 1: no angle requirement (thesis 4.3)
}

#: Chapter 5 (n = 6): Table 5.1; K_angle / K_bearing as in section 5.3 (0.3 for the scheme in use, 0 for the other).
_CH5: dict[str, Any] = {
    "n_agents": 6,
    "k_goal": 0.5,  # Table 5.1
    "k_dist": 1.0,  # Table 5.1
    "k_move": 0.3,  # Table 5.1
    "k_velocity": 0.1,  # Table 5.1
    "k_coll": 0.5,  # Table 5.1
    "k_time": 1.0,  # eq. 42
    "k_centroid": 1.0,  # eq. 42
    "r_c": 0.01,  # Table 5.1
    "r_reached": 4.0,  # Table 5.1
    "r_late": -10.0,  # Table 5.1
    "eta_g": 0.4,  # Table 5.1
    "eta_c": 1.2,  # Table 5.1
    "m_ang_deg": 30.0,  # Table 5.1; beta^ref = 120 deg is the interior angle for n = 6 (beta_ref_deg)
    "d_ref": 1.5,  # Table 5.1
    "d_comm": 3.0,  # Table 5.1
    "m_dist": 0.1,  # Table 5.1
    "k1": -1.1,  # Table 5.1
    "r_o": -5.0,  # Table 5.1
    "r_j": -1.0,  # Table 5.1
    "d_safe": 0.05,  # Table 5.1
    "chapter": "ch5",  # thesis 5.3
    # stage 1: centroid term only; stage 2: + neighbour distance; stage 3: + shape (docs/design.md "Curriculum placements")
    "stage_disabled_terms": (("dist", "angle", "bearing"), ("angle", "bearing"), ()),
}

#: The four thesis tasks. Any ``n_agents`` >= 3 may be combined with any of them.
TASKS: dict[str, dict[str, Any]] = {
    "ch4-individual": {**_CH4, "team_reward": False},  # thesis 4.1.1, Policy 1
    "ch4-team": {**_CH4, "team_reward": True},  # thesis 4.1.1 (team), Policy 2
    "ch5-angle": {**_CH5, "k_angle": 0.3, "k_bearing": 0.0},  # thesis 5.3, Policy 1
    "ch5-bearing": {**_CH5, "k_angle": 0.0, "k_bearing": 0.3},  # thesis 5.3, Policy 2
}
