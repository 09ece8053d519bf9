"""The engine's disturbed world: :class:`Disturber` draws and applies a task's
:class:`~sb3_formation.env.disturbances.Disturbances` to every team of a
:class:`~sb3_formation.env.engine.FormationEngine`, and :class:`MessageChannel` carries talking policies' messages
over lossy links.

Where each error enters a step (``docs/disturbances.md``):

- **acting**: the action an agent sends is recorded with its arrival time (the agent's delay, drawn once per
  episode, plus jitter); the world applies, in each part of the step, the newest action that has arrived (none: zero
  force), times the agent's motor gain, plus the step's force noise
  (:class:`~sb3_formation.env.dynamics.LateActions`);
- **sensing**: after the physics, every agent's estimate of its own position, velocity and heading (white error plus a
  drifting bias) replaces the truth in what the agents observe, and the formation of Table 3.1 (offsets, distances,
  angles, flags, centroid) is measured again from those estimates, so a row is consistent with itself; the lidar
  casts its rays turned by the agent's heading error, then adds range noise and drops beams;
- **timing**: each agent's observation is the one of ``observation_delay`` steps before (the reset's at first).

Rewards, info values, contacts and success stay those of the true world. Every draw comes from a team's own generator,
seeded from the team's episode seed (:meth:`Disturber.seed`), in a fixed order, so the same seed gives the same noise.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.disturbances import Communication, Disturbances, Failures, drift_correlation
from sb3_formation.env.dynamics import LateActions

#: The spawn key that gives the disturbances a stream of their own beside the scenario generator of the same seed.
DISTURBANCE_STREAM = 1
#: The spawn key of the failures' stream (the message links' is ``DISTURBANCE_STREAM + 1``).
FAILURE_STREAM = DISTURBANCE_STREAM + 2


def stream(seed: int, key: int = DISTURBANCE_STREAM) -> np.random.Generator:
    """The generator of the disturbances of seed ``seed``: independent of the scenario generator of that seed."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(key,)))


class FailureSchedule:
    """Which agent of each team fails in its episode, and at which step (:class:`~sb3_formation.env.disturbances.Failures`).

    A team's episode draws, at its reset and from a stream of its own (:data:`FAILURE_STREAM` of the team's seed),
    whether an agent fails, which (uniformly) and the step (uniformly in ``steps``), always all three, so the draws of
    one episode never shift another's. ``randomise`` does not scale the failures: their probability is already one per
    episode.

    :param failures: the task's failures
    :param sizes: ``(teams,)`` the teams' sizes n
    """

    def __init__(self, failures: Failures, sizes: np.ndarray) -> None:
        self.failures, self.sizes = failures, sizes
        self.generators = [stream(0, FAILURE_STREAM) for _ in sizes]
        #: each team's failing agent this episode (-1: none) and the step at whose end its motors stop
        self.agents, self.steps = np.full(len(sizes), -1), np.full(len(sizes), -1)

    def seed(self, team: int, seed: int) -> None:
        """Seed a team's generator from its scenario seed (:func:`stream`)."""
        self.generators[team] = stream(seed, FAILURE_STREAM)

    def reset(self, team: int) -> None:
        """Draw a team's episode: whether an agent fails, which one, and when."""
        generator, (low, high) = self.generators[team], self.failures.steps
        fails = generator.random() < self.failures.probability
        agent, step = int(generator.integers(self.sizes[team])), int(generator.integers(low, high + 1))
        self.agents[team], self.steps[team] = (agent, step) if fails else (-1, -1)

    def due(self, teams: list[int], step_counts: np.ndarray) -> list[tuple[int, int]]:
        """(team, agent) of the ``teams`` whose agent fails at the end of step ``step_counts[team]``."""
        return [(team, int(self.agents[team])) for team in teams if self.steps[team] == step_counts[team]]


class SensedTeams:
    """What the agents of some teams sensed in a step: their estimates and lidar errors.

    :param positions: ``(agents, 2)`` every agent's position estimate (m), the truth in rows not sensed
    :param velocities: ``(agents, 2)`` every agent's velocity estimate (m/s)
    :param heading_errors: ``(agents,)`` every agent's heading error (rad)
    :param beam_noise: ``(agents, rays)`` each beam's range error, as a share of the lidar's range
    :param dropped: ``(agents, rays)`` bool: the beam returned nothing
    """

    def __init__(
        self,
        positions: np.ndarray,
        velocities: np.ndarray,
        heading_errors: np.ndarray,
        beam_noise: np.ndarray,
        dropped: np.ndarray,
    ) -> None:
        self.positions, self.velocities, self.heading_errors = positions, velocities, heading_errors
        self.beam_noise, self.dropped = beam_noise, dropped


class Disturber:
    """Draws and applies one engine's disturbances (see the module docstring), team by team.

    Each team draws its episode (level, gains, delays, biases) at its reset, and its per-step errors as standard normal
    and uniform draws for :data:`BANK_STEPS` steps at a time (at its reset, then whenever they are used up), scaled by
    its agents' settings when used: the same seed gives the same draws, and a step applies every team's errors at once.

    :param config: the task (its ``disturbances``; teams may differ in ``n_agents`` only)
    :param starts: the first row of each team, then the number of rows
    :param observation_dim: the size of an observation
    """

    def __init__(self, config: FormationConfig, starts: np.ndarray, observation_dim: int) -> None:
        self.config, self.base = config, config.disturbances
        self.starts = starts
        n_teams, n_slots = len(starts) - 1, int(starts[-1])
        #: each row's team, and every row (the rows of all teams)
        self.team_of_row = np.repeat(np.arange(n_teams), np.diff(starts))
        self._every_row = np.arange(n_slots)
        largest = self.base.scaled(1.0)  # a randomised level is at most 1
        timing, sensing, acting = largest.timing, largest.sensing, largest.acting
        #: each team's generator and the disturbances of its episode (the level drawn when randomised)
        self.generators: list[np.random.Generator] = [stream(0) for _ in range(n_teams)]
        self.episodes: list[Disturbances] = [self.base] * n_teams
        self.levels = np.ones(n_teams)
        #: each agent's episode: motor gains, delays, the biases' current values, and the errors' scales
        self.gains, self.turn_gains = np.ones(n_slots), np.ones(n_slots)
        self.observation_delays = np.zeros(n_slots, dtype=np.int64)
        self.action_delays = np.zeros(n_slots)
        self.position_biases, self.heading_biases = np.zeros((n_slots, 2)), np.zeros(n_slots)
        self.scales = {name: np.zeros(n_slots) for name in _SCALES}
        #: actions sent and not yet superseded, in a ring of the last ``memory`` steps: step sent, arrival time (steps)
        self.memory = math.floor(timing.longest_action_delay) + 3
        self.sent_steps = np.full((self.memory, n_slots), -1, dtype=np.int64)
        self.arrivals = np.full((self.memory, n_slots), np.inf)
        self.sent = np.zeros((self.memory, n_slots, 2))
        self.late = timing.longest_action_delay > 0
        #: the observations of the last ``history`` steps, by step modulo ``history``
        self.history = np.zeros((timing.observation_delay[1] + 1, n_slots, observation_dim), dtype=np.float32)
        #: the lidar's errors, and the estimates', are drawn (else the lidar and the truth are what the agents read)
        self.lidar_errors = bool(sensing.lidar_noise or sensing.beam_dropout)
        self.localises = sensing.localises
        #: the motors apply something else than the actions sent
        self.acts = not acting.is_ideal or self.late
        # the draws of the errors that some team may have, BANK_STEPS steps ahead: sensing's, then acting's
        rays = config.lidar_rays
        shapes = {
            "position": (2,) if sensing.position_noise else None,
            "position_drift": (2,) if sensing.position_drift else None,
            "heading": () if sensing.heading_noise_deg else None,
            "heading_drift": () if sensing.heading_drift_deg else None,
            "velocity": (2,) if sensing.velocity_noise else None,
            "beam": (rays,) if sensing.lidar_noise else None,
            "dropout": (rays,) if sensing.beam_dropout else None,
            "force": (2,) if acting.force_noise else None,
            "jitter": () if timing.jitter else None,
        }
        self.banks = {
            name: np.zeros((BANK_STEPS, n_slots, *shape), dtype=np.float32 if name in _SINGLE_BANKS else np.float64)
            for name, shape in shapes.items()
            if shape is not None
        }
        self._sensing_banks: list[str] = [name for name in _SENSING_BANKS if name in self.banks]
        self._acting_banks: list[str] = [name for name in ("force", "jitter") if name in self.banks]
        self.cursors = {"sensing": np.zeros(n_teams, dtype=np.int64), "acting": np.zeros(n_teams, dtype=np.int64)}

    def seed(self, team: int, seed: int) -> None:
        """Seed a team's generator from its scenario seed (:func:`stream`)."""
        self.generators[team] = stream(seed)

    def reset(self, team: int, rows: slice) -> None:
        """Draw a team's episode: its level (when randomised), every agent's gains and delays, the biases' start (from
        their stationary law), the next steps' draws; forget the actions sent."""
        generator, n = self.generators[team], rows.stop - rows.start
        level = float(generator.uniform(0.0, 1.0)) if self.base.randomise else 1.0
        episode = self.episodes[team] = self.base.scaled(level) if self.base.randomise else self.base
        self.levels[team] = level
        acting, timing, sensing = episode.acting, episode.timing, episode.sensing
        self.gains[rows] = generator.uniform(*acting.gain, size=n) if acting.gain != (1.0, 1.0) else 1.0
        self.turn_gains[rows] = generator.uniform(*acting.turn_gain, size=n) if acting.turn_gain != (1.0, 1.0) else 1.0
        low, high = timing.observation_delay
        self.observation_delays[rows] = generator.integers(low, high + 1, size=n) if high > 0 else 0
        self.action_delays[rows] = generator.uniform(*timing.action_delay, size=n) if timing.action_delay[1] > 0 else 0.0
        position_drift, heading_drift = sensing.position_drift, math.radians(sensing.heading_drift_deg)
        self.position_biases[rows] = generator.normal(0.0, position_drift, size=(n, 2)) if position_drift else 0.0
        self.heading_biases[rows] = generator.normal(0.0, heading_drift, size=n) if heading_drift else 0.0
        self.sent_steps[:, rows], self.arrivals[:, rows], self.sent[:, rows] = -1, np.inf, 0.0
        for name, value in _scales(episode, self.config).items():
            self.scales[name][rows] = value
        for kind, names in (("sensing", self._sensing_banks), ("acting", self._acting_banks)):
            self._draw(team, names)
            self.cursors[kind][team] = 0

    def _draw(self, team: int, names: list[str]) -> None:
        """A team's next :data:`BANK_STEPS` steps of the draws ``names``, in their order."""
        generator, rows = self.generators[team], self._rows(team)
        for name in names:
            bank = self.banks[name]
            shape = (BANK_STEPS, rows.stop - rows.start, *bank.shape[2:])
            if name in _UNIFORM_BANKS:
                bank[:, rows] = generator.random(shape, dtype=bank.dtype)
            else:
                bank[:, rows] = generator.standard_normal(shape, dtype=bank.dtype)

    def _take(self, kind: str, teams: list[int], rows: np.ndarray) -> dict[str, np.ndarray]:
        """The draws of ``kind`` for this step of ``teams`` (their ``rows``): each bank's row of the team's cursor;
        the cursors move on, and a team whose draws are used up draws the next."""
        names = self._sensing_banks if kind == "sensing" else self._acting_banks
        cursors = self.cursors[kind]
        taken = {name: self.banks[name][cursors[self.team_of_row[rows]], rows] for name in names}
        cursors[teams] += 1
        for team in teams:
            if cursors[team] == BANK_STEPS:
                self._draw(team, names)
                cursors[team] = 0
        return taken

    def _rows(self, team: int) -> slice:
        return slice(int(self.starts[team]), int(self.starts[team + 1]))

    def _rows_of(self, teams: list[int]) -> np.ndarray:
        """The rows of ``teams``, in their order."""
        if len(teams) == len(self.generators):
            return self._every_row
        return np.concatenate([np.arange(self.starts[team], self.starts[team + 1]) for team in teams])

    # Sensing --------------------------------------------------------------------------------------------------------

    def sense(self, positions: np.ndarray, velocities: np.ndarray, teams: list[int], drift: bool) -> SensedTeams:
        """What the agents of ``teams`` sense of the true ``positions`` and ``velocities`` (every agent's rows):
        each agent's estimates (white error plus drifting bias; the velocity read in the frame its heading error turns)
        and its lidar's errors.

        :param drift: move the drifting biases on by a step first (not at a reset, whose biases were just drawn)
        """
        config, n_slots, scales = self.config, len(positions), self.scales
        rows = self._rows_of(teams)
        draws = self._take("sensing", teams, rows)
        sensed_positions, sensed_velocities = positions.copy(), velocities.copy()
        heading_errors = np.zeros(n_slots if self.localises else 0)
        beam_noise = np.zeros((n_slots, config.lidar_rays) if self.lidar_errors else (0, 0))
        dropped = np.zeros(beam_noise.shape, dtype=bool)
        if self.localises:
            keep = drift_correlation(self.base.sensing.drift_time, config.dt)
            fresh = math.sqrt(1.0 - keep * keep)
            if drift and "position_drift" in draws:
                step = scales["position_drift"][rows, None] * draws["position_drift"]
                self.position_biases[rows] = keep * self.position_biases[rows] + fresh * step
            if drift and "heading_drift" in draws:
                step = scales["heading_drift"][rows] * draws["heading_drift"]
                self.heading_biases[rows] = keep * self.heading_biases[rows] + fresh * step
            sensed_positions[rows] += self.position_biases[rows]
            if "position" in draws:
                sensed_positions[rows] += scales["position"][rows, None] * draws["position"]
            errors = self.heading_biases[rows]
            if "heading" in draws:
                errors = errors + scales["heading"][rows] * draws["heading"]
            heading_errors[rows] = errors
            cos, sin, v = np.cos(errors), np.sin(errors), velocities[rows]
            turned = np.stack([cos * v[:, 0] - sin * v[:, 1], sin * v[:, 0] + cos * v[:, 1]], axis=1)
            if "velocity" in draws:
                turned += scales["velocity"][rows, None] * draws["velocity"]
            sensed_velocities[rows] = turned
        if "beam" in draws:
            beam_noise[rows] = scales["beam"][rows, None] * draws["beam"]
        if "dropout" in draws:
            dropped[rows] = draws["dropout"] < scales["dropout"][rows, None]
        return SensedTeams(sensed_positions, sensed_velocities, heading_errors, beam_noise, dropped)

    def delay_observations(self, observations: np.ndarray, teams: list[int], step_counts: np.ndarray) -> None:
        """Replace, in place, the rows of ``teams`` in this step's ``observations`` by those of each agent's
        observation delay before (the reset's while the episode is younger), remembering this step's.

        :param step_counts: every team's steps since its reset, this step counted
        """
        memory = len(self.history)
        if memory == 1:
            return
        rows = self._rows_of(teams)
        now = step_counts[self.team_of_row[rows]]
        starting = rows[now == 0]
        self.history[:, starting] = observations[starting]
        self.history[now % memory, rows] = observations[rows]
        observations[rows] = self.history[(now - self.observation_delays[rows]) % memory, rows]

    # Acting ---------------------------------------------------------------------------------------------------------

    def act(self, actions: np.ndarray, teams: list[int], step_counts: np.ndarray) -> tuple[np.ndarray, LateActions | None]:
        """What the motors of the stepped ``teams`` apply: the sent ``actions`` (every agent's row) times the gains plus
        the step's force noise, or, with delays, the changes of action within the step (:class:`LateActions`).

        :param step_counts: every team's steps since its reset, before this step (the time the actions are sent)
        :return: the applied actions (rows of teams not stepped: as sent) and the late actions (``None`` without delays)
        """
        rows = self._rows_of(teams)
        draws = self._take("acting", teams, rows)
        noise = self.scales["force"][rows, None] * draws["force"] if "force" in draws else np.zeros((len(rows), 2))
        gains = np.stack(
            [self.gains[rows], self.turn_gains[rows] if self.config.dynamics == "unicycle" else self.gains[rows]], 1
        )
        applied = np.array(actions, dtype=np.float64)
        if not self.late:
            applied[rows] = applied[rows] * gains + noise
            return applied, None
        now = step_counts[self.team_of_row[rows]]
        slots = now % self.memory
        self.sent_steps[slots, rows], self.sent[slots, rows] = now, applied[rows]
        jitter = self.scales["jitter"][rows] * draws["jitter"] if "jitter" in draws else 0.0
        self.arrivals[slots, rows] = now + self.action_delays[rows] + jitter
        times, held, counts = arrival_changes(now.astype(np.float64), self.sent_steps[:, rows], self.arrivals[:, rows])
        sent = np.concatenate([self.sent[:, rows], np.zeros((1, len(rows), 2))])  # slot -1: nothing sent yet
        motor = sent[held, np.arange(len(rows))[:, None]] * gains[:, None, :] + noise[:, None, :]
        return applied, LateActions(times, motor, counts)


#: Steps of draws a team makes at once (:class:`Disturber`).
BANK_STEPS = 32
#: The draws of the sensing errors, in the order a team makes them; the uniform ones (the others are standard normal).
_SENSING_BANKS = ("position", "position_drift", "heading", "heading_drift", "velocity", "beam", "dropout")
_UNIFORM_BANKS = ("dropout", "jitter")
#: The draws kept in single precision: one per lidar beam, the most numerous (a range error of 1e-7 of a share)
_SINGLE_BANKS = ("beam", "dropout")
#: The per-agent scales of the draws (:func:`_scales`).
_SCALES = (*_SENSING_BANKS, "force", "jitter")


def _scales(episode: Disturbances, config: FormationConfig) -> dict[str, float]:
    """What multiplies each standard draw of an episode's errors: standard deviations (m, rad, m/s, shares of the
    lidar's range and of F_max), the jitter's width (steps); the dropout's probability (compared with a uniform draw)."""
    sensing = episode.sensing
    return {
        "position": sensing.position_noise,
        "position_drift": sensing.position_drift,
        "heading": math.radians(sensing.heading_noise_deg),
        "heading_drift": math.radians(sensing.heading_drift_deg),
        "velocity": sensing.velocity_noise,
        "beam": sensing.lidar_noise / config.lidar_range,
        "dropout": sensing.beam_dropout,
        "force": episode.acting.force_noise,
        "jitter": episode.timing.jitter,
    }


@numba.njit(cache=True)
def arrival_changes(
    now: np.ndarray, sent_steps: np.ndarray, arrivals: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """When, within the step from ``now`` to ``now + 1`` (steps, one per agent), each agent's action changes, and to
    which: at 0 the newest sent of those arrived (slot ``-1``: none yet), then each later arrival of a newer one,
    earliest first (of simultaneous ones the newest).

    :param sent_steps: ``(memory, k)`` the step each remembered action was sent (-1: none)
    :param arrivals: ``(memory, k)`` its arrival time (steps)
    :return: the times of the changes ``(k, memory + 1)`` (shares of the step, the first 0), the slot of the action
        from each change on ``(k, memory + 1)``, and each agent's number of changes ``(k,)``
    """
    memory, n = sent_steps.shape
    times = np.full((n, memory + 1), 1.0)
    slots = np.full((n, memory + 1), -1, dtype=np.int64)
    counts = np.zeros(n, dtype=np.int64)
    for agent in range(n):
        start = now[agent]
        newest, slot = -1, -1
        for k in range(memory):
            if sent_steps[k, agent] > newest and arrivals[k, agent] <= start:
                newest, slot = sent_steps[k, agent], k
        times[agent, 0], slots[agent, 0], count = 0.0, slot, 1
        while True:  # later arrivals within the step, earliest first (of simultaneous ones the newest), each newer
            best, best_time = -1, start + 1.0
            for k in range(memory):
                if sent_steps[k, agent] <= newest or not start < arrivals[k, agent] <= best_time:
                    continue
                if arrivals[k, agent] < best_time or (best >= 0 and sent_steps[k, agent] > sent_steps[best, agent]):
                    best, best_time = k, arrivals[k, agent]
            if best < 0 or best_time >= start + 1.0:
                break
            newest = sent_steps[best, agent]
            times[agent, count], slots[agent, count] = best_time - start, best
            count += 1
        counts[agent] = count
    return times, slots, counts


@numba.njit(cache=True)
def substep_plan(
    substeps: int, state: np.ndarray, late: LateActions, push: float, limits: tuple[float, float, bool]
) -> np.ndarray:  # pragma: no cover - compiled
    """Every agent's mean motion over each of a step's equal sub-steps under its changes of action
    (:class:`LateActions`), ``state`` moved on in place to the end of the step.

    A change gives an agent the velocity change of its action's force over the share of the step the action holds
    (eq. 19 over that share): a point's velocity ``clamp(v + a push h, v_max)``; a unicycle's forward speed
    ``clip(v + a_0 push h, +-v_max)`` and turn rate ``a_1 w_max``.

    :param state: ``(k, 2)`` a point's velocity (m/s), or a unicycle's forward speed (m/s) and turn rate (rad/s)
    :param push: the velocity change (m/s) of a unit force over a step
    :param limits: v_max (m/s), the unicycle's turn-rate limit (rad/s), and whether the agents are unicycles
    :return: ``(substeps, k, 2)`` the means of ``state`` over each sub-step
    """
    plan = np.zeros((substeps, state.shape[0], 2))
    for substep in range(substeps):
        plan[substep] = _substep_means(substep, substeps, state, late, push, limits)
    return plan


@numba.njit(cache=True)
def _substep_means(
    substep: int, substeps: int, state: np.ndarray, late: LateActions, push: float, limits: tuple[float, float, bool]
) -> np.ndarray:  # pragma: no cover - compiled
    """:func:`substep_plan`'s means over one sub-step, ``state`` moved on in place to its end."""
    v_max, turn_max, unicycle = limits
    low, high = substep / substeps, (substep + 1) / substeps
    means = np.zeros_like(state)
    for agent in range(state.shape[0]):
        count = late.counts[agent]
        for change in range(count):
            begin = late.times[agent, change]
            end = late.times[agent, change + 1] if change + 1 < count else 1.0
            if end <= low or begin >= high:
                continue
            if begin >= low:  # the change happens in this sub-step
                action, holds = late.actions[agent, change], end - begin
                if unicycle:
                    state[agent, 0] = min(max(state[agent, 0] + action[0] * push * holds, -v_max), v_max)
                    state[agent, 1] = action[1] * turn_max
                else:
                    x, y = state[agent, 0] + action[0] * push * holds, state[agent, 1] + action[1] * push * holds
                    speed = math.hypot(x, y)
                    scale = v_max / speed if speed > v_max else 1.0
                    state[agent, 0], state[agent, 1] = x * scale, y * scale
            share = (min(end, high) - max(begin, low)) * substeps
            means[agent, 0] += share * state[agent, 0]
            means[agent, 1] += share * state[agent, 1]
    return means


class MessageChannel:
    """Links that lose and delay the messages of a talking policy's agents (:class:`Communication`), for teams of
    ``n_agents`` stacked as a policy's rows (row k: agent ``k % n`` of team ``k // n``).

    Each agent receives, from its preceding and its succeeding ring neighbour, the message sent ``1 + d`` steps before
    (d the sender's extra delay, drawn per episode), unless that copy was lost (probability ``loss`` per link and step):
    then the last message that arrived on that link (zeros before the first).

    :param communication: the links' errors
    :param n_agents: agents per team
    :param n_teams: teams
    """

    def __init__(self, communication: Communication, n_agents: int, n_teams: int) -> None:
        self.communication, self.n_agents, self.n_teams = communication, n_agents, n_teams
        self.generators = [stream(0) for _ in range(n_teams)]
        n_rows = n_agents * n_teams
        self.delays = np.zeros(n_rows, dtype=np.int64)
        self.past: np.ndarray | None = None  # (delay + 1, rows, M) the messages sent in the last steps, newest first
        self.heard: np.ndarray | None = None  # (rows, 2, M) the last message that arrived on each link
        self.steps = np.zeros(n_teams, dtype=np.int64)
        neighbours = (np.arange(n_agents)[:, None] + np.array([-1, 1])) % n_agents
        self.senders = (np.arange(n_teams)[:, None, None] * n_agents + neighbours[None]).reshape(n_rows, 2)

    def start(self, team: int, seed: int) -> None:
        """Start a team's episode of seed ``seed``: its links' generator and delays; nothing heard."""
        generator = self.generators[team] = stream(seed, key=DISTURBANCE_STREAM + 1)
        rows = slice(team * self.n_agents, (team + 1) * self.n_agents)
        low, high = self.communication.delay
        self.delays[rows] = generator.integers(low, high + 1, size=self.n_agents) if high > 0 else 0
        self.steps[team] = 0
        if self.past is not None and self.heard is not None:
            self.past[:, rows] = 0.0
            self.heard[rows] = 0.0

    def deliver(self, sent: np.ndarray, senders: np.ndarray | None = None) -> np.ndarray:
        """What every row receives at this step from its ring neighbours, ``(rows, 2, M)``, given the messages
        ``(rows, M)`` that every row sent at its last step.

        :param senders: ``(rows, 2)`` the rows of each row's neighbours (``None``: the ring of n; a team with a failed
            agent: its flying agents' ring, :func:`~sb3_formation.env.geometry.flying_rows`)
        """
        sent = np.asarray(sent, dtype=np.float32)
        if self.past is None or self.heard is None or self.past.shape[2] != sent.shape[1]:
            self.past = np.zeros((self.communication.delay[1] + 1, *sent.shape), dtype=np.float32)
            self.heard = np.zeros((sent.shape[0], 2, sent.shape[1]), dtype=np.float32)
        self.past = np.concatenate([sent[None], self.past[:-1]])
        n_rows = len(sent)
        lost = np.zeros((n_rows, 2), dtype=bool)
        for team, generator in enumerate(self.generators):
            rows = slice(team * self.n_agents, (team + 1) * self.n_agents)
            if self.communication.loss:
                lost[rows] = generator.random((self.n_agents, 2)) < self.communication.loss
        senders = self.senders if senders is None else senders
        delays = self.delays[senders]  # (rows, 2): the sender's extra delay
        arriving = self.past[delays, senders]  # (rows, 2, M)
        team_steps = self.steps[np.arange(n_rows) // self.n_agents]
        sent_yet = delays < team_steps[:, None]  # sent in this episode (a message of a step before it never arrives)
        keep = lost | ~sent_yet
        heard: np.ndarray = np.where(keep[:, :, None], self.heard, arriving)
        self.heard = heard
        self.steps += 1
        delivered: np.ndarray = heard.copy()
        return delivered
