"""The safety filter: discrete-time control barrier functions, one small QP per agent, from its own observation row.

``docs/safety.md`` has the equations; in short, for one agent, from its row of thesis Table 3.1 only:

- **Model.** The agent controls a point: its centre (holonomic) or, for a unicycle, the point ``l = v_max / w_max``
  ahead of its axle that the controllers already steer (:class:`~sb3_formation.env.dynamics.UnicycleModel`, its
  ``look_ahead``); the task's :class:`~sb3_formation.env.dynamics.DynamicsModel` gives the filter this model
  (``point_problem``, ``point_actions``).
  Over a step the point moves by ``u dt``, u the velocity its action commands (holonomic: v' = clamp(v + a F_max dt / m);
  unicycle: ``v' h + l w h_perp``). The filter chooses u.
- **Barriers.** Each constraint is a barrier h >= 0 with the discrete-time condition ``h(t+1) >= (1 - gamma) h(t)``,
  written linearly in u. A lidar return q (either channel) is a point of a body's surface: ``h = |q - P| - r - margin``,
  P the controlled point and r the radius of the disc round P that holds the agent (R_a, or R_a + l for a unicycle);
  since ``|q - P|`` is convex in P, ``g . u dt <= gamma h`` with g the unit vector from P to q keeps h's condition
  (a conservative linearisation). A ring neighbour at offset d: ``h = |d| - 2 R_a - margin`` (no collision) and
  ``h = d_comm - margin - |d|`` (stay within communication range, the thesis's formation constraint); agents share
  these, each taking half of gamma h. The range barrier is concave in the offset, so its linearisation is corrected by
  its largest second-order error ``(2 u_max dt)^2 / (2 |d|)``.
- **Hard constraints.** The action bounds (holonomic: ``|a_x|, |a_y| <= 1``; unicycle: forward force and turn rate
  within theirs) and the speed limit as a circumscribed polygon of ``speed_sides`` sides (the env's speed clamp only
  shortens u, which keeps every constraint whose right-hand side is >= 0).
- **QP.** The closest u to the proposed one with penalised slack (:mod:`sb3_formation.safety.qp`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any, NamedTuple

import numba
import numpy as np

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.disturbances import Disturbances
from sb3_formation.env.dynamics import clip_speed, dynamics_model
from sb3_formation.env.observations import observation_fields, observation_layout
from sb3_formation.env.scenes import scenes_named
from sb3_formation.env.sensors import ray_directions
from sb3_formation.safety.qp import solve_rows, solve_with_library
from sb3_formation.utils.checks import is_integer, is_number

#: Solvers of the filter's QP: ``fast`` (the compiled exact solver) or a solver of ``qpsolvers``.
SOLVERS = ("fast", "daqp", "quadprog", "proxqp", "osqp", "clarabel")
#: The most constraints one agent's QP can have beyond its lidar rays: 2 x 2 neighbour barriers, 4 action bounds,
#: the speed polygon's sides and the slack's sign.
_FIXED_CONSTRAINTS = 4 + 4 + 1


@dataclass(frozen=True)
class SafetyGains:
    """Gains and margins of :class:`SafetyFilter` (``docs/safety.md``).

    :param gamma: the barriers' decay rate in (0, 1]: ``h(t+1) >= (1 - gamma) h(t)``; smaller approaches more slowly
    :param obstacle_margin: gap (m) kept from every obstacle and wall the lidar sees
    :param agent_margin: gap (m) kept from every other agent
    :param comm_margin: distance (m) kept inside the communication range d_comm from each ring neighbour
    :param keep_comm_range: keep each ring neighbour within d_comm - comm_margin (the formation constraint)
    :param slack_weight: rho, the penalty on the slack (in units of a step's travel v_max dt) against the change of
        the commanded velocity (in units of v_max)
    :param infeasible_slack: a step is reported infeasible when its QP needed more slack than this (fraction of v_max dt)
    :param speed_sides: sides of the circumscribed polygon that stands for the speed limit
    :param solver: ``"fast"`` (compiled, exact) or a ``qpsolvers`` solver name (:data:`SOLVERS`)
    :param obstacle_speed: the declared bound (m/s) on the speed of anything the lidar's obstacle channel sees (moving
        obstacles, pedestrians): every obstacle return is kept as if it approached at this speed (worst case), over
        the step and over the declared delay; ``None``: the bound the task's scenes declare
        (:meth:`~sb3_formation.env.scenarios.Scenes.obstacle_speed`: 0 where obstacles stand still)
    """

    gamma: float = 0.5
    obstacle_margin: float = 0.01
    agent_margin: float = 0.01
    comm_margin: float = 0.1
    keep_comm_range: bool = True
    slack_weight: float = 1e4
    infeasible_slack: float = 1e-3
    speed_sides: int = 16
    solver: str = "fast"
    obstacle_speed: float | None = None

    def __post_init__(self) -> None:
        for item in fields(self):
            value = getattr(self, item.name)
            if item.name == "keep_comm_range":
                valid, allowed = isinstance(value, bool), "true or false"
            elif item.name == "solver":
                valid, allowed = value in SOLVERS, f"one of {list(SOLVERS)}"
            elif item.name == "speed_sides":
                valid, allowed = is_integer(value) and 4 <= value <= 64, "an integer from 4 to 64"
            elif item.name == "gamma":
                valid, allowed = is_number(value) and 0 < value <= 1, "a number in (0, 1]"
            elif item.name == "slack_weight":
                valid, allowed = is_number(value) and 1.0 <= value <= 1e8, "a number from 1 to 1e8"
            elif item.name == "obstacle_speed":
                valid, allowed = value is None or (is_number(value) and value >= 0), "a finite number >= 0 or null"
            else:
                valid, allowed = is_number(value) and value >= 0, "a finite number >= 0"
            if not valid:
                raise ValueError(f"SafetyGains.{item.name}={value!r} is invalid: it must be {allowed}")

    @classmethod
    def from_dict(cls, values: dict[str, Any] | None) -> SafetyGains:
        """Gains from a mapping of field names (a recipe's ``safety:`` section); ``None`` gives the defaults.

        :raises ValueError: a name that is not a field (the valid ones are listed)
        """
        values = dict(values or {})
        names = [item.name for item in fields(cls)]
        unknown = sorted(set(values) - set(names))
        if unknown:
            raise ValueError(f"unknown safety filter setting(s) {unknown}; settings: {names}")
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        """Every field as plain data."""
        return {item.name: getattr(self, item.name) for item in fields(self)}


@dataclass
class FilterReport:
    """What the filter did to a batch of rows.

    :param changed: ``(k,)`` the action was changed
    :param change: ``(k,)`` size of the change |a_safe - a| (fraction of F_max; 0 where unchanged)
    :param infeasible: ``(k,)`` the constraints could not all be kept (the QP needed slack above ``infeasible_slack``)
    :param separation: ``(k,)`` the smallest gap (m) the agent's sensors measure to an obstacle, a wall or an agent
    """

    changed: np.ndarray
    change: np.ndarray
    infeasible: np.ndarray
    separation: np.ndarray


#: Standard deviations of a Gaussian error that the filter takes as its bound: 99.7 % of draws lie within 3 of a
#: scalar error (:data:`TAIL_SIGMAS`), and within 3.41 per-axis deviations of a 2-D error of equal axes
#: (:data:`TAIL_SIGMAS_2D`, sqrt(-2 ln 0.003)).
TAIL_SIGMAS = 3.0
TAIL_SIGMAS_2D = math.sqrt(-2.0 * math.log(0.003))


@dataclass(frozen=True)
class FilterBounds:
    """What the filter assumes of the errors it cannot see (``docs/disturbances.md``, "A filter that stays safe").
    Bounded errors within these are covered; a Gaussian error is bounded by :data:`TAIL_SIGMAS` standard deviations,
    so its tails are measured, not guaranteed.

    :param range_error: bound (m) on a lidar range's error
    :param position_error: bound (m) on the distance between an agent's position estimate and the truth
    :param offset_error: bound (m) on the error of the offset between two agents' estimates (the difference of their
        errors; default ``2 position_error``, both at their bound in opposite directions)
    :param heading_error: bound (rad) on an agent's heading error (it turns what the agent reads)
    :param velocity_error: bound (m/s) on the error of an agent's velocity estimate
    :param delay: ``(low, high)`` steps from the instant an observation was sensed to the arrival of the action
        chosen from it (observation delay plus action delay and jitter)
    :param jitter: steps by which an action may arrive earlier or later than the whole delays the filter predicts over,
        so that each sent action may hold that much longer or shorter than a step
    :param gain: ``(low, high)`` motor gains
    :param force_error: bound (share of F_max) on the force noise
    :param fill_dropped: a beam that returns nothing between two that see something reads as the nearer of them
    """

    range_error: float = 0.0
    position_error: float = 0.0
    offset_error: float | None = None
    heading_error: float = 0.0
    velocity_error: float = 0.0
    delay: tuple[float, float] = (0.0, 0.0)
    jitter: float = 0.0
    gain: tuple[float, float] = (1.0, 1.0)
    force_error: float = 0.0
    fill_dropped: bool = False

    @classmethod
    def declared(cls, disturbances: Disturbances, tail: float = 1.0) -> FilterBounds:
        """The bounds of a task's disturbances (their largest level when randomised): :data:`TAIL_SIGMAS` standard
        deviations of each scalar Gaussian error, :data:`TAIL_SIGMAS_2D` of each 2-D one (white and drifting parts
        combined), both times ``tail``; the delays' and gains' intervals. Two agents' position errors are drawn
        independently, so the error of their offset has sqrt(2) times one's deviation."""
        sensing, acting, timing = disturbances.sensing, disturbances.acting, disturbances.timing
        position = math.hypot(sensing.position_noise, sensing.position_drift)
        heading = math.radians(math.hypot(sensing.heading_noise_deg, sensing.heading_drift_deg))
        scalar, planar = tail * TAIL_SIGMAS, tail * TAIL_SIGMAS_2D
        return cls(
            range_error=scalar * sensing.lidar_noise,
            position_error=planar * position,
            offset_error=planar * math.sqrt(2.0) * position if position > 0 else None,
            heading_error=scalar * heading,
            velocity_error=planar * sensing.velocity_noise,
            delay=(
                timing.observation_delay[0] + timing.action_delay[0],
                timing.observation_delay[1] + timing.longest_action_delay,
            ),
            jitter=timing.jitter,
            gain=(min(acting.gain[0], acting.turn_gain[0]), max(acting.gain[1], acting.turn_gain[1])),
            force_error=planar * acting.force_noise,
            fill_dropped=sensing.beam_dropout > 0,
        )

    @property
    def is_exact(self) -> bool:
        """No error: the filter of the ideal world."""
        return self == FilterBounds()

    @property
    def neighbour_offset_error(self) -> float:
        """(m) the bound on the error of a ring neighbour's offset: :attr:`offset_error`, else twice
        :attr:`position_error`."""
        return 2.0 * self.position_error if self.offset_error is None else self.offset_error

    @property
    def horizon(self) -> int:
        """Whole steps of sent actions the filter predicts over (the delay's upper bound, rounded up)."""
        return math.ceil(self.delay[1] - 1e-9)


class SentCommands:
    """The last actions each row's agent sent (after the filter), newest last, for the filter's prediction over a delay.

    :param horizon: how many are kept
    """

    def __init__(self, horizon: int) -> None:
        self.horizon = horizon
        self.actions = np.zeros((0, horizon, 2))

    def rows(self, count: int, episode_start: np.ndarray | None) -> np.ndarray:
        """The kept actions ``(count, horizon, 2)`` of ``count`` rows, forgotten where an episode starts (and for every
        row when the number of rows changed)."""
        if len(self.actions) != count:
            self.actions = np.zeros((count, self.horizon, 2))
        elif episode_start is not None:
            self.actions[np.asarray(episode_start, dtype=bool).reshape(-1)] = 0.0
        return self.actions

    def add(self, actions: np.ndarray) -> None:
        """Keep the actions ``(count, 2)`` just sent."""
        if self.horizon:
            self.actions = np.concatenate([self.actions[:, 1:], np.asarray(actions, dtype=np.float64)[:, None]], axis=1)


class FilterConstants(NamedTuple):
    """What stays fixed for a filter's life, as its compiled constraint builder reads it."""

    directions: np.ndarray  #: ``(n_rays, 2)`` ray directions
    columns: np.ndarray  #: int64: the start columns of lidar_obstacles, lidar_agents and neighbour_offsets in a row
    #: gamma, obstacle_margin, agent_margin, comm_margin, keep_comm_range (0/1), neighbour_margin, and the approach (m)
    #: of an obstacle at the declared speed over a step
    gains: np.ndarray
    speed_normals: np.ndarray  #: ``(sides, 2)`` outward normals of the speed polygon (none for a unicycle)
    speed_limit: float  #: the polygon's apothem (units of v_max)
    lidar_range: float  #: l_s (m)
    radius: float  #: R_a (m)
    v_max: float  #: (m/s)
    dt: float  #: (s)
    d_comm: float  #: the communication range (m)


class Constraints(NamedTuple):
    """Every agent's QP (:mod:`~sb3_formation.safety.qp`): its constraint rows, right-hand sides and count, and the
    smallest gap its sensors measure; written by the constraint builder."""

    rows: np.ndarray  #: ``(k, m, 3)`` rows ``(g_x, g_y, -1)`` (safety) or ``(a_x, a_y, 0)`` (hard)
    rhs: np.ndarray  #: ``(k, m)`` right-hand sides
    counts: np.ndarray  #: ``(k,)`` int64: the rows used
    separation: np.ndarray  #: ``(k,)`` the smallest gap (m) to an obstacle, a wall or an agent

    @classmethod
    def zeros(cls, count: int, capacity: int) -> Constraints:
        """No constraint yet for ``count`` agents of at most ``capacity`` constraints each."""
        return cls(
            np.zeros((count, capacity, 3)), np.zeros((count, capacity)), np.zeros(count, dtype=np.int64), np.zeros(count)
        )


@numba.njit(cache=True)
def _add_row(
    rows: np.ndarray, rhs: np.ndarray, count: int, projection: np.ndarray, direction: np.ndarray, bound: float
) -> int:  # pragma: no cover - compiled
    """Append the safety constraint ``direction . (projection u) - s <= bound``; return the new count."""
    rows[count, 0] = direction[0] * projection[0, 0] + direction[1] * projection[1, 0]
    rows[count, 1] = direction[0] * projection[0, 1] + direction[1] * projection[1, 1]
    rows[count, 2] = -1.0
    rhs[count] = bound
    return count + 1


@numba.njit(cache=True)
def _tightest(candidates: np.ndarray, count: int, longest: float, out: np.ndarray) -> float:  # pragma: no cover
    """One constraint ``g . x <= b`` (x the controlled point's move over the step, at most ``longest`` m long) that
    implies every candidate ``(g_x, g_y, b)`` of ``candidates[:count]``: the direction of the one of smallest b, and
    the smallest ``b_i - |g_i - g| longest`` (``g_i . x <= g . x + |g_i - g| |x|``). Writes the direction into ``out``
    and returns the bound (m)."""
    best = 0
    for index in range(1, count):
        if candidates[index, 2] < candidates[best, 2]:
            best = index
    out[0], out[1] = candidates[best, 0], candidates[best, 1]
    bound = candidates[best, 2]
    for index in range(count):
        turn = math.hypot(candidates[index, 0] - out[0], candidates[index, 1] - out[1])
        bound = min(bound, candidates[index, 2] - turn * longest)
    return bound


@numba.njit(cache=True)
def _build_constraints(
    observations: np.ndarray,
    projections: np.ndarray,
    bounds: np.ndarray,
    constants: FilterConstants,
    out: Constraints,
    shifts: np.ndarray,
    slips: np.ndarray,
) -> None:  # pragma: no cover - compiled; tested through its results
    """Every agent's constraint rows (see the module docstring), in units of v_max (u) and v_max dt (h), into ``out``.

    :param observations: ``(k, obs_dim)`` raw rows
    :param projections: ``(k, 2, 2)`` the map from the controlled point's velocity to the centre's: the identity for
        a holonomic agent, ``h h^T`` for a unicycle (its centre moves along its heading h with the forward speed h . u)
    :param bounds: ``(k, 4, 3)`` each agent's four action-bound rows (a_x, a_y, b) in units of v_max
    :param constants: the filter's constants
    :param shifts: ``(k, s, 2)`` where each agent may be (m, from where it sensed its row) when its action arrives, one
        row per delay of the window (none: where it is)
    :param slips: ``(k, s, 2)`` for each of those delays, what the agent's step under the new action moves (m) beyond
        ``u dt``, u reckoned from the row's velocity (the velocity it will have then minus that one, times dt). Each
        barrier is kept over the step from every one of those positions: linearised there (conservative: h(p + x) >=
        h(p) - g . x), its move ``u dt + slip``; one constraint per barrier implies them all (:func:`_tightest`)
    """
    directions, columns, gains, speed_normals = (
        constants.directions,
        constants.columns,
        constants.gains,
        constants.speed_normals,
    )
    lidar_range, radius, v_max, dt, d_comm = (
        constants.lidar_range,
        constants.radius,
        constants.v_max,
        constants.dt,
        constants.d_comm,
    )
    speed_limit, rows, rhs, counts, separation = constants.speed_limit, out.rows, out.rhs, out.counts, out.separation
    gamma, obstacle_margin, agent_margin, comm_margin, keep_comm = gains[0], gains[1], gains[2], gains[3], gains[4]
    neighbour_margin, approach = gains[5], gains[6]
    step = v_max * dt  # m: the unit of h
    reach = speed_limit * step  # m: the longest move of the controlled point in a step
    n_rays = directions.shape[0]
    # the longest u dt the hard constraints allow: the speed polygon's corners (a unicycle: the action box's)
    sides = speed_normals.shape[0]
    longest = reach / math.cos(math.pi / sides) if sides > 0 else reach
    window = shifts.shape[1]
    candidates = np.empty((max(window, 1), 3))
    moved = np.empty(2)
    for agent in range(observations.shape[0]):
        row = observations[agent]
        projection = projections[agent]
        count = 0
        nearest = np.inf
        for channel in range(2):
            share = 1.0 if channel == 0 else 0.5  # agents share a barrier; an obstacle may approach at the bound
            margin = obstacle_margin if channel == 0 else agent_margin
            closing = approach if channel == 0 else 0.0
            for ray in range(n_rays):
                reading = row[columns[channel] + ray]
                if reading >= 1.0:
                    continue
                gap = reading * lidar_range
                nearest = min(nearest, gap)
                if window == 0:
                    bound = share * gamma * (gap - margin) - closing  # h = |q - p| - R_a - margin, |q - p| = R_a + gap
                    direction = directions[ray]
                else:
                    for shift in range(window):  # the surface point q seen from where the agent may be
                        qx = (radius + gap) * directions[ray, 0] - shifts[agent, shift, 0]
                        qy = (radius + gap) * directions[ray, 1] - shifts[agent, shift, 1]
                        distance = max(math.hypot(qx, qy), 1e-12)
                        gx, gy = qx / distance, qy / distance
                        candidates[shift, 0], candidates[shift, 1] = gx, gy
                        slip = gx * slips[agent, shift, 0] + gy * slips[agent, shift, 1]
                        candidates[shift, 2] = share * gamma * (distance - radius - margin) - slip - closing
                    bound = _tightest(candidates, window, longest, moved)
                    direction = moved
                if bound < reach:  # else it cannot bind within a step's move
                    count = _add_row(rows[agent], rhs[agent], count, projection, direction, bound / step)
        for side in range(2):  # the ring neighbours: their offsets (as estimated)
            offset = row[columns[2] + 2 * side : columns[2] + 2 * side + 2]
            centres = math.hypot(offset[0], offset[1])
            nearest = min(nearest, centres - 2 * radius)
            if window == 0:
                if centres <= 0.0:
                    continue
                bound = 0.5 * gamma * (centres - 2 * radius - neighbour_margin)
                if bound < reach:
                    count = _add_row(rows[agent], rhs[agent], count, projection, offset / centres, bound / step)
                if keep_comm > 0.5:
                    curvature = (2 * reach) ** 2 / (2 * centres)  # the linearisation's largest error (m)
                    bound = 0.5 * (gamma * (d_comm - comm_margin - centres) - curvature)
                    if bound < reach:
                        count = _add_row(rows[agent], rhs[agent], count, projection, -offset / centres, bound / step)
                continue
            closest = np.inf
            for shift in range(window):  # the neighbour seen from where the agent may be
                ox, oy = offset[0] - shifts[agent, shift, 0], offset[1] - shifts[agent, shift, 1]
                closest = min(closest, math.hypot(ox, oy))
            if closest <= 0.0:
                continue
            for shift in range(window):  # no collision: h = |d| - 2 R_a - margin, convex in d
                ox, oy = offset[0] - shifts[agent, shift, 0], offset[1] - shifts[agent, shift, 1]
                distance = math.hypot(ox, oy)
                gx, gy = ox / distance, oy / distance
                slip = gx * slips[agent, shift, 0] + gy * slips[agent, shift, 1]
                candidates[shift, 0], candidates[shift, 1] = gx, gy
                candidates[shift, 2] = 0.5 * gamma * (distance - 2 * radius - neighbour_margin) - slip
            bound = _tightest(candidates, window, longest, moved)
            if bound < reach:
                count = _add_row(rows[agent], rhs[agent], count, projection, moved, bound / step)
            if keep_comm > 0.5:
                for shift in range(window):  # within range: h = d_comm - margin - |d|, concave: corrected
                    ox, oy = offset[0] - shifts[agent, shift, 0], offset[1] - shifts[agent, shift, 1]
                    distance = math.hypot(ox, oy)
                    gx, gy = -ox / distance, -oy / distance
                    slip = gx * slips[agent, shift, 0] + gy * slips[agent, shift, 1]
                    curvature = (2 * reach) ** 2 / (2 * distance)  # the linearisation's largest error (m)
                    candidates[shift, 0], candidates[shift, 1] = gx, gy
                    candidates[shift, 2] = 0.5 * (gamma * (d_comm - comm_margin - distance) - curvature) - slip
                bound = _tightest(candidates, window, longest, moved)
                if bound < reach:
                    count = _add_row(rows[agent], rhs[agent], count, projection, moved, bound / step)
        separation[agent] = nearest
        for bound in range(4):
            rows[agent, count, 0], rows[agent, count, 1], rows[agent, count, 2] = (
                bounds[agent, bound, 0],
                bounds[agent, bound, 1],
                0.0,
            )
            rhs[agent, count] = bounds[agent, bound, 2]
            count += 1
        for side in range(speed_normals.shape[0]):
            rows[agent, count, 0], rows[agent, count, 1], rows[agent, count, 2] = (
                speed_normals[side, 0],
                speed_normals[side, 1],
                0.0,
            )
            rhs[agent, count] = speed_limit
            count += 1
        rows[agent, count, 0], rows[agent, count, 1], rows[agent, count, 2] = 0.0, 0.0, -1.0  # s >= 0
        rhs[agent, count] = 0.0
        count += 1
        counts[agent] = count


class SafetyFilter:
    """The decentralised safety filter: the closest actions that keep each agent's barriers, from its own row.

    :param config: the task (dynamics, sizes, lidar, v_max, dt, d_comm)
    :param gains: gains and margins (defaults: :class:`SafetyGains`)
    :param bounds: the errors it stays safe under (default: those the task's disturbances declare,
        :meth:`FilterBounds.declared`; none in the ideal world)
    """

    def __init__(self, config: FormationConfig, gains: SafetyGains | None = None, bounds: FilterBounds | None = None) -> None:
        self.config = config
        self.gains = gains if gains is not None else SafetyGains()
        self.bounds = bounds if bounds is not None else FilterBounds.declared(config.disturbances)
        observed = observation_fields(config)
        layout = observation_layout(observed)
        #: observation field name -> slice of a row, and a row's width
        self.layout, self.observation_dim = layout, sum(item.size for item in observed)
        columns = [layout["lidar_obstacles"].start, layout["lidar_agents"].start, layout["neighbour_offsets"].start]
        #: the task's dynamics: the point an agent steers and how its actions move it
        self.model = dynamics_model(config)
        # the speed limit: a polygon round the disc for holonomic agents; a unicycle's action bounds are its limits
        sides = 0 if self.model.bounds_speed else self.gains.speed_sides
        angles = (np.arange(sides) + 0.5) * (2 * math.pi / max(sides, 1))
        speed_normals = np.stack([np.cos(angles), np.sin(angles)], axis=1)
        speed_limit = 1.0 / math.cos(math.pi / self.gains.speed_sides) if sides else math.sqrt(2.0)  # the apothem
        #: velocity change (m/s) of a unit force action over a step
        self._push = config.force_max * config.dt / config.agent_mass
        #: how far ahead of its centre the point an agent steers lies (m): a unicycle's l = v_max / w_max, else 0
        self.lookahead = self.model.look_ahead
        g = self.gains
        obstacle, agent, neighbour = self._robust_margins(speed_limit)
        #: (m/s) the bound on the obstacles' speed the filter keeps the agents safe under
        self.obstacle_speed = (
            scenes_named(config.scenes).obstacle_speed(config) if g.obstacle_speed is None else g.obstacle_speed
        )
        obstacle += self.obstacle_speed * config.dt * self.bounds.delay[1]  # an obstacle's unseen move over the delay
        margins = [g.obstacle_margin + obstacle, g.agent_margin + agent, g.comm_margin + neighbour]
        approach = self.obstacle_speed * config.dt  # m: how far an obstacle at the bound closes in over the step
        self._constants = FilterConstants(
            directions=ray_directions(config.lidar_rays),
            columns=np.array(columns, dtype=np.int64),
            gains=np.array([g.gamma, *margins, float(g.keep_comm_range), g.agent_margin + neighbour, approach]),
            speed_normals=speed_normals,
            speed_limit=float(speed_limit),
            lidar_range=float(config.lidar_range),
            radius=float(config.agent_radius),
            v_max=float(config.v_max),
            dt=float(config.dt),
            d_comm=float(config.d_comm),
        )
        self._capacity = 2 * config.lidar_rays + _FIXED_CONSTRAINTS + sides
        #: whole steps of delay the filter predicts over (a unicycle's prediction is the margin of its longest move)
        predicts = self.bounds.horizon > 0 and not self.model.bounds_speed
        self._delays = np.arange(math.floor(self.bounds.delay[0]), self.bounds.horizon + 1) if predicts else np.zeros(0, int)

    def _robust_margins(self, speed_limit: float) -> tuple[float, float, float]:
        """The gaps (m) the declared :attr:`bounds` add to the margins from obstacles, from agents the lidar sees and
        from ring neighbours (``docs/disturbances.md``): the range error; what the heading error turns a step's move
        by; what the velocity error, the motor gains, the force noise and the jitter add to the move of the step and
        of every step of the delay (a velocity error of at most 2 v_max: the true and the predicted velocity are both
        within v_max); the longest delay's move of another agent (and of the agent itself where it is not
        predicted); the error of the offset between two agents' estimates."""
        bounds, config = self.bounds, self.config
        if bounds.is_exact:
            return 0.0, 0.0, 0.0
        step = config.v_max * config.dt  # m
        push = config.force_max * config.dt / config.agent_mass  # m/s of a unit action over a step
        reach = speed_limit * step
        steps = bounds.horizon + 1  # the delay's whole steps and the step of the action itself
        # the velocity error after k steps: the estimate's; each step's gain error and the change between two sent
        # actions (at most 2 sqrt 2) acting up to `jitter` of a step longer or shorter, piled up (k times); the force
        # noise, drawn anew each step, as a sum of k independent draws (sqrt k times one's bound)
        per_step = (max(bounds.gain[1] - 1.0, 1.0 - bounds.gain[0]) + 2.0 * bounds.jitter) * math.sqrt(2.0) * push
        errors = [bounds.velocity_error + k * per_step + math.sqrt(k) * bounds.force_error * push for k in range(1, steps + 1)]
        drift = sum(min(error, 2.0 * config.v_max) for error in errors) * config.dt
        turned = reach * 2.0 * math.sin(min(bounds.heading_error, math.pi) / 2.0) * steps
        own = 0.0 if not self.model.bounds_speed else bounds.horizon * reach  # a unicycle's move over the delay
        obstacle = bounds.range_error + turned + drift + own
        other = bounds.delay[1] * reach  # another agent's move over the delay, unseen
        return obstacle, obstacle + other, drift + turned + own + other + bounds.neighbour_offset_error

    def filter(
        self, observations: np.ndarray, actions: np.ndarray, sent: np.ndarray | None = None
    ) -> tuple[np.ndarray, FilterReport]:
        """Safe actions ``(k, 2)`` for ``(k, obs_dim)`` raw rows and their proposed ``(k, 2)`` actions (float32 or
        float64, kept; anything else becomes float64), and what the filter did. Each row is filtered from itself alone
        (and, under a declared delay, the actions its agent sent before, ``sent`` ``(k, h, 2)`` newest last:
        :class:`SentCommands`); rows whose actions keep every constraint come back as they were (after clipping to
        [-1, 1]). Under a window of delays (more than one whole delay declared) an action the env's speed clamp would
        shorten comes back as the one that commands its clamped velocity without the clamp: from the velocity of another
        delay of the window the clamp would turn it into another move than the one the filter kept.

        :raises ValueError: rows or actions of the wrong shape, rows or actions that are not finite, or rows so far out of
            range that the safe actions would not be (the filter never returns a non-finite action)
        """
        observations = np.asarray(observations, dtype=np.float64)
        proposed = np.asarray(actions)
        if proposed.dtype not in (np.float32, np.float64):
            proposed = proposed.astype(np.float64)
        width = self.observation_dim
        if observations.ndim != 2 or observations.shape[1] != width:
            raise ValueError(f"the safety filter takes (k, {width}) observation rows, got shape {observations.shape}")
        if proposed.shape != (len(observations), 2):
            raise ValueError(f"the safety filter takes ({len(observations)}, 2) actions, got shape {proposed.shape}")
        if not np.isfinite(proposed).all():
            raise ValueError("the safety filter got actions that are not finite (NaN or inf)")
        if not np.isfinite(observations).all():
            raise ValueError("the safety filter got observation rows that are not finite (NaN or inf)")
        proposed = np.clip(proposed, -1.0, 1.0)
        count = len(observations)
        shifts = slips = np.zeros((count, 0, 2))
        if self.bounds.fill_dropped:
            observations = self._filled(observations)
        if len(self._delays):
            observations, shifts, slips = self._predicted(observations, sent)
        velocity = observations[:, self.layout["velocity"]]
        targets, projections, bounds, frames = self.model.point_problem(
            observations, self.layout, proposed.astype(np.float64), self._push
        )
        constraints = Constraints.zeros(count, self._capacity)
        _build_constraints(observations, projections, bounds, self._constants, constraints, shifts, slips)
        rows, rhs, counts, separation = constraints.rows, constraints.rhs, constraints.counts, constraints.separation
        if self.gains.solver == "fast":
            solutions = solve_rows(targets, self.gains.slack_weight, rows, rhs, counts)
        else:
            solutions = np.stack(
                [
                    solve_with_library(
                        targets[k], self.gains.slack_weight, rows[k, : counts[k]], rhs[k, : counts[k]], self.gains.solver
                    )
                    for k in range(count)
                ]
            )
        changed = (solutions[:, 0] != targets[:, 0]) | (solutions[:, 1] != targets[:, 1])
        safe = proposed.copy()
        exact = changed
        if len(self._delays) > 1:  # an action the speed clamp shortens would command, at another delay, other than u
            exact = changed | (np.linalg.norm(velocity + self._push * proposed, axis=1) > self.config.v_max)
        if exact.any():
            actions = self.model.point_actions(solutions[exact, :2], velocity[exact], frames[exact], self._push)
            safe[exact] = actions.astype(safe.dtype)
        if not np.isfinite(safe).all():  # finite rows beyond any reachable state (e.g. 1e300 m) can overflow
            raise ValueError("the safety filter could not keep these rows' actions finite: their values are out of range")
        change = np.where(changed, np.linalg.norm(safe - proposed, axis=1), 0.0)
        infeasible = solutions[:, 2] > self.gains.infeasible_slack
        return safe, FilterReport(changed, change, infeasible, separation)

    def _filled(self, observations: np.ndarray) -> np.ndarray:
        """Rows whose dropped beams (a beam that sees nothing between two that see something) read as the nearer of
        their neighbours, on both lidar channels."""
        rows, rays = observations.copy(), self.config.lidar_rays
        for name in ("lidar_obstacles", "lidar_agents"):
            readings = rows[:, self.layout[name]]
            before, after = np.roll(readings, 1, axis=1), np.roll(readings, -1, axis=1)
            dropped = (readings >= 1.0) & (before < 1.0) & (after < 1.0) if rays > 2 else np.zeros_like(readings, bool)
            rows[:, self.layout[name]] = np.where(dropped, np.minimum(before, after), readings)
        return rows

    def _predicted(self, observations: np.ndarray, sent: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where each agent may be when the action chosen now arrives: for each whole delay d of the window, its move
        (m) from where it sensed its row under the d actions it sent last (oldest first; eq. 19 from the row's
        velocity), and what its step under the new action then moves otherwise than the filter reckons from the
        velocity of the longest delay, which the rows returned carry (``(k, delays, 2)`` shifts and slips)."""
        config, horizon, count = self.config, self.bounds.horizon, len(observations)
        history = np.zeros((count, horizon, 2)) if sent is None else np.asarray(sent, dtype=np.float64)
        history = history[:, history.shape[1] - horizon :] if history.ndim == 3 else history
        if history.shape != (count, horizon, 2):
            raise ValueError(f"the safety filter takes ({count}, {horizon}, 2) sent actions, got shape {history.shape}")
        start = observations[:, self.layout["velocity"]]
        moves, velocities = np.zeros((count, len(self._delays), 2)), np.zeros((count, len(self._delays), 2))
        for index, delay in enumerate(self._delays):
            velocity, moved = start.copy(), np.zeros((count, 2))
            for step in range(horizon - delay, horizon):
                velocity = clip_speed(velocity + np.clip(history[:, step], -1.0, 1.0) * self._push, config.v_max)
                moved += velocity * config.dt
            moves[:, index], velocities[:, index] = moved, velocity
        reckoned = velocities[:, -1]
        rows = observations.copy()
        rows[:, self.layout["velocity"]] = reckoned
        return rows, moves, (velocities - reckoned[:, None]) * config.dt
