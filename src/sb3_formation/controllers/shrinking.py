"""The shrinking controller: a decentralised formation that shrinks to the free space it sees and follows obstacles
on a side the whole team agrees on, without communication.

Every agent acts from its own observation row (Table 3.1), its index i and the config, plus its own memory of its
own past observations (the ``state`` of :meth:`ShrinkingController.predict`, reset on ``episode_start``). Agreement
comes from values every agent of a team observes identically: the centroid-goal offset c_g and its change
Delta c_g. Each agent knows its own offset from the centroid, o_i = p_i - p_c = c_g - d_g.

- **Team heading** (shared memory). The centroid moves at ``v_c = V R(sigma phi) c_g / |c_g|``, V = k_goal v_max:
  the goal direction turned by phi >= 0 to the side sigma in {-1, +1}. V may exceed v_max: each agent's command is
  clipped to v_max, so the team still moves at full speed along a wall its heading presses on at an angle alpha while
  V cos(alpha) >= v_max. The team's progress along the last heading h,
  ``P <- (1 - a) P + a (-Delta c_g . h) / (V dt)``, is a bump sensor: while P < p_block (blocked) the heading turns
  away, ``phi <- phi + omega_block`` (on the way to the goal, phi = 0, only after ``patience`` blocked steps, time for
  the formation to shrink into an opening); while free it turns back, ``phi <- max(phi - omega_free, 0)``
  (``omega_back`` while phi > 90 deg: round the end of an obstacle). The team so follows an obstacle's boundary on
  the side sigma and leaves it where the way to the goal is free.
- **Wall search** (shared memory; ``wall_search``, the default). A detour begins when the team has been blocked for
  ``patience`` steps on its way to the goal. Its side sigma is the side the centroid drifted to,
  ``sigma = sign(c_g x (-Delta c_g))`` (its running mean; +1 on a tie), and the heading turns by phi_0 at once. The
  team keeps the hit point ``H = -c_g`` (the centroid's offset from the goal), the hit distance ``d_h = |c_g|``
  (lowered whenever it is blocked closer) and the wall's normal n at H: the direction of the mean shortfall of its
  steps, ``h + Delta c_g / (V dt)``, while it waited pressed on the wall. With p = -c_g the centroid's offset now, leg
  k (after k flips) ends when the centroid is ``D 2^k`` along the wall from H, ``|n x (p - H)| > D 2^k``, or when it
  is E behind H heading away from the wall, ``-n . (p - H) > E`` and ``h . n < 0`` (a dead end: a corner, the
  world's border; E is the same for every leg). Then the team turns back the way it came at once
  (``phi <- |pi - phi|``, ``sigma <- -sigma``): the cow-path search of the wall's unknown end, doubling on alternate
  sides. After a dead end that side is closed: legs no longer end on their length, only at the next dead end. No leg
  ends while the team rounds the end of a wall (phi more than ``round_deg`` below its largest value at a blocked step
  of the leg): it has found a way round. The detour ends, freeing sigma for the next obstacle, once the heading is
  back on the goal (phi = 0) and ``|c_g| < d_h - leave_margin``. Every input is shared, so every agent of a team
  holds the same search (phi, sigma, H, n, d_h, k).

  *Bound.* Along a straight infinite wall whose opening lies d along it from H, the centroid travels
  ``2 D (2^j - 1) + d`` along the wall until it is abreast of the opening, j being the first leg on the opening's
  side with ``D 2^j >= d`` (leg j - 2, on the same side, fell short); so at most ``max(2 D + d, 9 d - 2 D)``, within
  9 times the direct path d once d >= D / 4, and ``9 d + 2 D`` for any d. That is the competitive ratio of the
  doubling search on a line, the least any deterministic search achieves (Baeza-Yates, Culberson and Rawlins,
  *Searching in the plane*, Information and Computation 106, 1993). Each leg ends at the first step past its length,
  adding at most one step's travel V dt each way, and the agents reverse at their force limit (holonomic agents
  within ``2 m v_max / (F_max dt)`` steps, 2 in the thesis's tasks). Assumptions: nothing but the wall is in the way; the team
  follows it at a constant distance (never E behind H); it turns round the wall's end at the opening before its leg
  ends; n is the wall's normal (an error epsilon stretches every leg by 1 / cos(epsilon)). Not guaranteed: the time
  (the speed along the wall is the bump sensor's), walls that bend or end in a bounded world (a dead end ends a leg
  early), the first side.
- **Bug2-like detour** (``wall_search=False``: the rule ``pretrained:scenes-ch5-bearing`` was trained with). The
  detour starts at the first blocked step (sigma and d_h as above) and turns by omega_block per step once the team
  has waited ``patience`` steps; it keeps the anchor ``d_a = |c_g|`` and, after k flips, turns back
  (``phi <- |pi - phi|``, ``sigma <- -sigma``, ``d_a <- |c_g|``) when it has led ``D_flip 2^k`` further from the goal
  than the anchor, ``|c_g| > d_a + D_flip 2^k``, or turned past phi_max. It ends as the wall search does.
- **Scale** (per agent, agreed with the neighbours). From the obstacle lidar's gaps g_k (m): the proximity scale
  ``s_p = s_min + (1 - s_min) clip((min_k g_k - g_lo) / (g_hi - g_lo), 0, 1)`` and the width scale
  ``s_w = (w / 2 - R_a - m_w) / r_0`` with ``w = min_k (g_k + g_{k+b/2} + 2 R_a)`` over opposite rays that both see
  something (the width of the opening the agent stands in); the neighbours' scale is what their distances show,
  ``s_n = min_j |d_j| / L + delta``. Then ``s_i <- clip(min(s_p, s_w, s_n, s_i + rho), s_min, 1)``: a neighbour that
  shrinks pulls the side in and the whole ring follows; the team grows back by at most rho per step.
  ``s_min = (2 R_a + gap_min) / L``.
- **Agent command**: ``v_i = v_c + k_place (s_i r_0 u_i - o_i) + k_obstacle F_lidar(g; s_0) + k_agent (F_agents +
  F_neighbours)``, with u_i the unit vertex i of the reference n-gon, r_0 and L the starting circumradius and side,
  F the 1/s - 1/s_0 lidar repulsion of :mod:`~sb3_formation.controllers.classical` (obstacles within s_0, other
  agents within l_s) and ``F_neighbours`` pushing from a neighbour whose surface gap is below ``neighbour_range``.
  The placement terms sum to zero over a team, so the centroid moves at v_c plus the mean of the repulsions.
- **Actuation**: :func:`~sb3_formation.controllers.classical.command_action`, ``F = m (v* - v) / dt`` (a unicycle
  follows v* by feedback linearisation).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sb3_formation.controllers.base import (
    AgentStep,
    Controller,
    RingShape,
    check_gains,
    no_messages,
    ring_groups,
    ring_shape,
)
from sb3_formation.controllers.classical import MIN_GAP, command_action, lidar_repulsion, unit
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.sensors import ray_directions

#: Columns of one agent's memory (a row of the ``state`` array of :meth:`ShrinkingController.predict`).
MEMORY_FIELDS = (
    "phi",
    "sigma",
    "anchor",
    "scale",
    "progress",
    "lateral",
    "heading_x",
    "heading_y",
    "flips",
    "hit",
    "waited",
    "started",
    "hit_x",
    "hit_y",
    "shortfall_x",
    "shortfall_y",
    "peak",
    "closed",
)
_PHI, _SIGMA, _ANCHOR, _SCALE, _PROGRESS, _LATERAL, _HX, _HY, _FLIPS, _HIT, _WAITED, _STARTED = range(12)
_HIT_X, _HIT_Y, _SHORT_X, _SHORT_Y, _PEAK, _CLOSED = range(12, len(MEMORY_FIELDS))  # the wall search's own


@dataclass(frozen=True)
class ShrinkingGains:
    """Gains of :class:`ShrinkingController` (see the module docstring); defaults tuned for teams of 6 in the
    ch5-bearing task on seeds 0-39 and 100-139 of every family and of stage 3, the wall search's and k_goal on seeds
    0-199 of the corridor family, apart from the benchmark's seeds. Teams of 4 do as well with them; teams of 8 pass
    openings and corridors more often with ``block_progress=0.55`` (they must press harder into an opening to
    squeeze through).

    :param k_goal: team speed V as a fraction of v_max (above 1: full speed along a wall pressed on at an angle)
    :param k_place: gain (1/s) from the distance to the agent's place in the formation to its speed
    :param k_obstacle: obstacle and wall repulsion (m^2/s per radian of rays)
    :param k_agent: repulsion of other agents (lidar) and of close neighbours (m^2/s)
    :param repulsion_range: reach s_0 (m) of the obstacle repulsion
    :param neighbour_range: reach (m) of a neighbour's repulsion, surface to surface
    :param progress_rate: a, the weight of the last step in the running progress P
    :param block_progress: p_block: the team is blocked while P is below this fraction of V dt
    :param patience: steps a team blocked on its way to the goal waits (shrinking) before it turns aside
    :param turn_block_deg: omega_block (deg per step), the heading's turn away while blocked
    :param turn_free_deg: omega_free (deg per step), its turn back while free
    :param turn_back_deg: omega_back (deg per step), its turn back while free and turned by more than 90 deg (going
        round the end of an obstacle)
    :param max_turn_deg: phi_max (deg), Bug2-like detour: turning further is a dead end, the side flips
    :param flip_distance: D_flip (m), Bug2-like detour: a detour that takes the centroid this much further from the
        goal than its anchor flips side (twice as much after each flip)
    :param leave_margin: the detour (its side and flips) ends when the centroid is this much (m) closer to the goal
        than anywhere it was blocked, heading on the goal
    :param gap_low: g_lo (m): an obstacle this close shrinks the agent's scale to s_min
    :param gap_high: g_hi (m): an obstacle farther than this does not shrink it
    :param width_margin: m_w (m): room each side of the formation in an opening
    :param min_side_gap: gap_min (m): the smallest formation's neighbours keep this much room between surfaces
    :param scale_slack: delta: a scale at most this much above what the neighbours' distances show
    :param scale_relax: rho: the most the scale grows per step
    :param wall_search: detour by the wall search; false: by the Bug2-like detour (the rule of the residual policies
        trained before the wall search)
    :param search_distance: D (m), wall search: leg k ends D 2^k along the wall from the hit point
    :param search_back: E (m), wall search: a leg ends when the team heads away from the wall this far behind the
        hit point (a dead end)
    :param search_turn_deg: phi_0 (deg), wall search: the heading's turn when a detour begins
    :param round_deg: wall search: no leg ends while phi is this much (deg) below its largest value at a blocked step
        of the leg (the team is rounding the end of a wall)
    """

    k_goal: float = 1.2
    k_place: float = 0.3
    k_obstacle: float = 0.004
    k_agent: float = 0.002
    repulsion_range: float = 0.4
    neighbour_range: float = 0.15
    progress_rate: float = 0.1
    block_progress: float = 0.65
    patience: float = 40.0
    turn_block_deg: float = 1.0
    turn_free_deg: float = 0.85
    turn_back_deg: float = 2.0
    max_turn_deg: float = 200.0
    flip_distance: float = 2.5
    leave_margin: float = 0.5
    gap_low: float = 0.2
    gap_high: float = 0.8
    width_margin: float = 0.02
    min_side_gap: float = 0.05
    scale_slack: float = 0.05
    scale_relax: float = 0.002
    wall_search: bool = True
    search_distance: float = 3.0
    search_back: float = 3.0
    search_turn_deg: float = 60.0
    round_deg: float = 40.0

    def __post_init__(self) -> None:
        check_gains(self)
        if self.gap_high <= self.gap_low:
            raise ValueError(f"ShrinkingGains.gap_high={self.gap_high!r} must exceed gap_low={self.gap_low!r}")
        if not 0 < self.progress_rate <= 1:
            raise ValueError(f"ShrinkingGains.progress_rate={self.progress_rate!r} must lie in (0, 1]")
        if self.search_distance <= 0:
            raise ValueError(f"ShrinkingGains.search_distance={self.search_distance!r} must be > 0 (the first leg's length)")


class ShrinkingController(Controller):
    """A formation that shrinks to the free space and follows obstacles on an agreed side (see the module docstring),
    decentralised, with a memory per agent of its own past observations.

    :meth:`predict` (and :meth:`agent_step`) take and return the memory as SB3's ``state``: a float array
    ``(k, len(MEMORY_FIELDS))``, one row per observation row, reset where ``episode_start`` is true (or when ``state``
    is ``None``).
    :meth:`act` without memory acts as on the first step of an episode.

    :param config: the task configuration
    :param gains: keyword values of :class:`ShrinkingGains`
    """

    def __init__(self, config: FormationConfig, **gains: Any) -> None:
        super().__init__(config)
        self.settings = self._take_gains(ShrinkingGains, gains)
        self._fit_task()

    def _fit_task(self) -> None:
        config = self.config
        self.directions = ray_directions(config.lidar_rays)

    # Memory ------------------------------------------------------------------------------------------------------

    def initial_memory(self, rows: int) -> np.ndarray:
        """The memory of ``rows`` agents at the start of an episode: heading on the goal, full scale, progress free."""
        memory = np.zeros((rows, len(MEMORY_FIELDS)))
        memory[:, _SCALE] = 1.0
        memory[:, _PROGRESS] = 1.0
        return memory

    def _agent_step(
        self,
        observations: np.ndarray,
        agents: np.ndarray,
        state: Any,
        episode_start: np.ndarray | None,
        received: np.ndarray | None,
        deterministic: bool,
    ) -> AgentStep:
        """Actions for rows of any agents and their memory as the next state (reset where ``episode_start``).

        :raises ValueError: a memory that is not ``(k, len(MEMORY_FIELDS))`` numbers
        """
        observations = np.asarray(observations, dtype=np.float64)
        memory = self.initial_memory(len(observations))
        if state is not None:
            memory = np.array(state, dtype=np.float64)
            if memory.shape != (len(observations), len(MEMORY_FIELDS)):
                raise ValueError(
                    f"the shrinking controller's state is its memory of shape ({len(observations)}, {len(MEMORY_FIELDS)}),"
                    f" got {memory.shape}"
                )
            if episode_start is not None:
                starts = np.asarray(episode_start, dtype=bool).reshape(-1)
                memory[starts] = self.initial_memory(int(starts.sum()))
        actions, memory = self.step(observations, agents, memory)
        return AgentStep(np.clip(actions, -1.0, 1.0).astype(np.float32), memory, no_messages(len(observations)))

    def act(self, observations: np.ndarray, agents: np.ndarray, deterministic: bool) -> np.ndarray:
        return self.step(observations, agents, self.initial_memory(len(observations)))[0]

    def step(self, observations: np.ndarray, agents: np.ndarray, memory: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Actions ``(k, 2)`` and the next memory for rows of agents with their memory (``(k, len(MEMORY_FIELDS))``).

        :param observations: ``(k, obs_dim)`` raw observations
        :param agents: ``(k,)`` each row's agent index in its team, or ``(k, 2)`` its place and ring size
            (:func:`~sb3_formation.controllers.base.ring_places`): its place on the polygon of its ring
        :param memory: ``(k, len(MEMORY_FIELDS))`` each agent's memory (not changed)
        """
        layout, gains, config = self.layout, self.settings, self.config
        memory = memory.copy()
        heading = self.team_heading(
            observations[:, layout["centroid_goal_offset"]], observations[:, layout["centroid_goal_offset_change"]], memory
        )
        obstacles = observations[:, layout["lidar_obstacles"]]
        offsets = observations[:, layout["neighbour_offsets"]].reshape(-1, 2, 2)
        own = observations[:, layout["centroid_goal_offset"]] - observations[:, layout["goal_offset"]]
        places = np.empty((len(observations), 2))
        for rows, spots, size in ring_groups(agents, config.n_agents):  # each ring's polygon, of its size
            ring = ring_shape(config, size)
            memory[rows, _SCALE] = self.agreed_scale(obstacles[rows], offsets[rows], memory[rows, _SCALE], ring)
            places[rows] = memory[rows, _SCALE, None] * ring.circumradius * ring.vertices[spots]
        velocity = gains.k_goal * config.v_max * heading + gains.k_place * (places - own)
        velocity += gains.k_obstacle * lidar_repulsion(obstacles, config, self.directions, gains.repulsion_range)
        velocity += gains.k_agent * lidar_repulsion(observations[:, layout["lidar_agents"]], config, self.directions)
        velocity += gains.k_agent * close_neighbour_repulsion(offsets, config.agent_radius, gains.neighbour_range)
        return command_action(velocity, observations, layout, config), memory

    # Parts -------------------------------------------------------------------------------------------------------

    def team_heading(self, goal: np.ndarray, goal_change: np.ndarray, memory: np.ndarray) -> np.ndarray:
        """The unit heading of the centroid, updating the shared part of ``memory`` in place (phi, sigma, the detour's
        state, progress, lateral drift, last heading) from the shared c_g and Delta c_g only.

        :param goal: ``(k, 2)`` centroid-to-goal offsets c_g (m)
        :param goal_change: ``(k, 2)`` their change over the last step (m)
        :param memory: ``(k, len(MEMORY_FIELDS))`` memories, updated
        """
        gains, config = self.settings, self.config
        step_length = max(gains.k_goal * config.v_max * config.dt, 1e-300)
        direction = unit(goal)
        distance = np.linalg.norm(goal, axis=1)
        moved = -goal_change
        started = memory[:, _STARTED] > 0
        last = memory[:, [_HX, _HY]]
        progress = (moved * last).sum(axis=1) / step_length
        lateral = (direction[:, 0] * moved[:, 1] - direction[:, 1] * moved[:, 0]) / step_length
        rate = gains.progress_rate
        memory[:, _PROGRESS] = np.where(started, (1 - rate) * memory[:, _PROGRESS] + rate * progress, memory[:, _PROGRESS])
        memory[:, _LATERAL] = np.where(started, (1 - rate) * memory[:, _LATERAL] + rate * lateral, memory[:, _LATERAL])
        blocked = started & (memory[:, _PROGRESS] < gains.block_progress)
        phi, sigma, anchor = memory[:, _PHI], memory[:, _SIGMA], memory[:, _ANCHOR]
        hit, flipped, waited = memory[:, _HIT], memory[:, _FLIPS], memory[:, _WAITED]
        ends = (hit > 0) & (phi <= 0) & (distance < hit - gains.leave_margin)
        hit[:] = np.where(ends, 0.0, hit)
        waited[:] = np.where(blocked, waited + 1, 0.0)
        begins = (hit <= 0) & (waited > gains.patience) if gains.wall_search else blocked & (hit <= 0)
        side = np.where(memory[:, _LATERAL] < 0, -1.0, 1.0)
        sigma[:] = np.where(begins, side, sigma)
        anchor[:] = np.where(begins, distance, anchor)
        hit[:] = np.where(begins, distance, np.where(blocked & (hit > 0), np.minimum(hit, distance), hit))
        flipped[:] = np.where(begins, 0.0, flipped)
        turn_block = math.radians(gains.turn_block_deg)
        turn_free = np.radians(np.where(phi > math.pi / 2, gains.turn_back_deg, gains.turn_free_deg))
        turning = blocked & ((phi > 0) | (waited > gains.patience))
        phi[:] = np.where(turning, phi + turn_block, np.where(blocked, phi, np.maximum(phi - turn_free, 0.0)))
        if gains.wall_search:
            flips = self.search_flips(goal, moved, blocked, begins, memory)
        else:  # the Bug2-like detour: flip D_flip 2^k further from the goal than the anchor, or turned past phi_max
            away = distance > anchor + gains.flip_distance * 2.0**flipped
            flips = (hit > 0) & (phi > 0) & (away | (phi > math.radians(gains.max_turn_deg)))
        flipped[:] = np.where(flips, flipped + 1, flipped)
        # turned by pi, the team goes back the way it came (the wall search exactly: past pi, phi < 0 heads on the goal)
        phi[:] = np.where(flips, math.pi - phi if gains.wall_search else np.abs(math.pi - phi), phi)
        sigma[:] = np.where(flips, -sigma, sigma)
        anchor[:] = np.where(flips, distance, anchor)
        heading = rotate(direction, np.where(phi > 0, sigma, 0.0) * phi)
        memory[:, [_HX, _HY]] = heading
        memory[:, _STARTED] = 1.0
        return heading

    def search_flips(
        self, goal: np.ndarray, moved: np.ndarray, blocked: np.ndarray, begins: np.ndarray, memory: np.ndarray
    ) -> np.ndarray:
        """The wall search's part of :meth:`team_heading`: which rows turn back now, updating the search's memory (hit
        point, wall normal, first turn, largest blocked turn, closed side; the bump sensor re-armed on a new heading).

        :param goal: ``(k, 2)`` centroid-to-goal offsets c_g (m)
        :param moved: ``(k, 2)`` the centroid's last step, -Delta c_g (m)
        :param blocked: ``(k,)`` rows whose progress P is below p_block
        :param begins: ``(k,)`` rows whose detour begins now (phi, sigma and d_h already set)
        :param memory: ``(k, len(MEMORY_FIELDS))`` memories, updated
        """
        gains = self.settings
        phi, hit, peak, closed = memory[:, _PHI], memory[:, _HIT], memory[:, _PEAK], memory[:, _CLOSED]
        place = -goal  # the centroid's offset from the goal, the same for every agent of a team
        step_length = max(gains.k_goal * self.config.v_max * self.config.dt, 1e-300)
        # the wall's normal: the mean shortfall of the steps while the team waits pressed on it, frozen in the detour
        shortfall = memory[:, [_SHORT_X, _SHORT_Y]]
        mean = shortfall + gains.progress_rate * (memory[:, [_HX, _HY]] - moved / step_length - shortfall)
        kept = np.where((hit > 0)[:, None], shortfall, 0.0)
        memory[:, [_SHORT_X, _SHORT_Y]] = np.where(((hit <= 0) & blocked)[:, None], mean, kept)
        memory[:, [_HIT_X, _HIT_Y]] = np.where(begins[:, None], place, memory[:, [_HIT_X, _HIT_Y]])
        phi[:] = np.where(begins, math.radians(gains.search_turn_deg), phi)
        closed[:] = np.where(begins, 0.0, closed)
        normal, way = unit(memory[:, [_SHORT_X, _SHORT_Y]]), place - memory[:, [_HIT_X, _HIT_Y]]
        along = np.abs(way[:, 0] * normal[:, 1] - way[:, 1] * normal[:, 0])
        heading = rotate(unit(goal), memory[:, _SIGMA] * phi)
        dead_end = (-(way * normal).sum(axis=1) > gains.search_back) & ((heading * normal).sum(axis=1) < 0)
        leg_done = (along > gains.search_distance * 2.0 ** memory[:, _FLIPS]) & (closed <= 0)
        peak[:] = np.where(begins, phi, np.where(blocked, np.maximum(peak, phi), peak))
        rounding = phi < peak - math.radians(gains.round_deg)
        flips = (hit > 0) & (phi > 0) & ~rounding & (leg_done | dead_end)
        closed[:] = np.where(flips & dead_end, 1.0, closed)
        peak[:] = np.where(flips, 0.0, peak)
        memory[:, _PROGRESS] = np.where(begins | flips, 1.0, memory[:, _PROGRESS])
        return flips

    def agreed_scale(self, obstacles: np.ndarray, offsets: np.ndarray, previous: np.ndarray, ring: RingShape) -> np.ndarray:
        """Each agent's formation scale: the least of what its obstacle lidar allows (:meth:`lidar_scale`), what its
        neighbours' distances show plus delta, and its last scale plus rho, within [s_min, 1].

        :param obstacles: ``(k, rays)`` obstacle lidar readings (fractions of the range)
        :param offsets: ``(k, 2, 2)`` neighbour offsets (m)
        :param previous: ``(k,)`` the agents' last scales
        :param ring: the agents' ring (:func:`~sb3_formation.controllers.base.ring_shape`)
        """
        gains = self.settings
        neighbours = np.linalg.norm(offsets, axis=-1).min(axis=1) / ring.side_length + gains.scale_slack
        scale = np.minimum(np.minimum(self.lidar_scale(obstacles, ring), neighbours), previous + gains.scale_relax)
        return np.clip(scale, self.min_scale(ring), 1.0)

    def min_scale(self, ring: RingShape) -> float:
        """s_min: the scale at which the ring's sides leave ``min_side_gap`` between neighbours (at most 1)."""
        return min(1.0, (2 * self.config.agent_radius + self.settings.min_side_gap) / ring.side_length)

    def lidar_scale(self, obstacles: np.ndarray, ring: RingShape) -> np.ndarray:
        """The scale the obstacle lidar allows: the least of the proximity scale s_p and the width scale s_w.

        :param obstacles: ``(k, rays)`` obstacle lidar readings (fractions of the range)
        :param ring: the agents' ring
        """
        gains, config, min_scale = self.settings, self.config, self.min_scale(ring)
        gaps = obstacles * config.lidar_range
        nearest = gaps.min(axis=1)
        proximity = min_scale + (1 - min_scale) * np.clip(
            (nearest - gains.gap_low) / (gains.gap_high - gains.gap_low), 0.0, 1.0
        )
        half = gaps.shape[1] // 2
        seen = obstacles < 1.0
        both = seen[:, :half] & seen[:, half : 2 * half]
        widths = np.where(both, gaps[:, :half] + gaps[:, half : 2 * half], np.inf).min(axis=1) + 2 * config.agent_radius
        width = (widths / 2 - config.agent_radius - gains.width_margin) / ring.circumradius
        return np.minimum(proximity, width)


def rotate(vectors: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Rows of ``vectors`` turned anti-clockwise by ``angles`` (rad)."""
    cos, sin = np.cos(angles), np.sin(angles)
    return np.stack([cos * vectors[:, 0] - sin * vectors[:, 1], sin * vectors[:, 0] + cos * vectors[:, 1]], axis=1)


def close_neighbour_repulsion(offsets: np.ndarray, agent_radius: float, reach: float) -> np.ndarray:
    """Push ``(1/s - 1/reach)`` away from each designated neighbour whose surface gap s is below ``reach`` (m).

    :param offsets: ``(k, 2, 2)`` neighbour offsets (m)
    :param agent_radius: R_a (m)
    :param reach: reach (m) of the push
    """
    if reach <= 0:
        return np.zeros((len(offsets), 2))
    gaps = np.maximum(np.linalg.norm(offsets, axis=-1) - 2 * agent_radius, MIN_GAP)
    push = np.where(gaps < reach, 1.0 / gaps - 1.0 / reach, 0.0)
    return -(push[..., None] * unit(offsets)).sum(axis=1)
