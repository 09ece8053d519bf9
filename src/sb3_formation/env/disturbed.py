"""The engine's disturbed world: :class:`Disturber` draws and applies a task's
:class:`~sb3_formation.env.disturbances.Disturbances` to every team of a
:class:`~sb3_formation.env.engine.FormationEngine`, and :class:`MessageChannel` carries talking policies' messages
over lossy links.

Where each error enters a step (``docs/disturbances.md``):

- **acting**: the action an agent sends is recorded with its arrival time (the agent's delay, drawn once per
  episode, plus jitter); the world applies, in each part of the step, the newest action that has arrived (none: zero
  force), times the agent's motor gain, plus the step's force noise
  (:class:`~sb3_formation.env.dynamics.ActionSchedule`);
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
from sb3_formation.env.disturbances import Communication, Disturbances, drift_correlation
from sb3_formation.env.dynamics import ActionSchedule

#: The spawn key that gives the disturbances a stream of their own beside the scenario generator of the same seed.
DISTURBANCE_STREAM = 1


def stream(seed: int, key: int = DISTURBANCE_STREAM) -> np.random.Generator:
    """The generator of the disturbances of seed ``seed``: independent of the scenario generator of that seed."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(key,)))


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

    :param config: the task (its ``disturbances``; teams may differ in ``n_agents`` only)
    :param starts: the first row of each team, then the number of rows
    :param observation_dim: the size of an observation
    """

    def __init__(self, config: FormationConfig, starts: np.ndarray, observation_dim: int) -> None:
        self.config, self.base = config, config.disturbances
        self.starts = starts
        n_teams, n_slots = len(starts) - 1, int(starts[-1])
        largest = self.base.scaled(1.0)  # a randomised level is at most 1
        timing = largest.timing
        #: each team's generator and the disturbances of its episode (the level drawn when randomised)
        self.generators: list[np.random.Generator] = [stream(0) for _ in range(n_teams)]
        self.episodes: list[Disturbances] = [self.base] * n_teams
        self.levels = np.ones(n_teams)
        self.gains, self.turn_gains = np.ones(n_slots), np.ones(n_slots)
        self.observation_delays = np.zeros(n_slots, dtype=np.int64)
        self.action_delays = np.zeros(n_slots)
        self.position_biases, self.heading_biases = np.zeros((n_slots, 2)), np.zeros(n_slots)
        #: actions sent and not yet superseded, in a ring of the last ``memory`` steps: step sent, arrival time (steps)
        self.memory = math.floor(timing.longest_action_delay) + 3
        self.sent_steps = np.full((self.memory, n_slots), -1, dtype=np.int64)
        self.arrivals = np.full((self.memory, n_slots), np.inf)
        self.sent = np.zeros((self.memory, n_slots, 2))
        self.late = timing.longest_action_delay > 0
        #: the observations of the last ``history`` steps, by step modulo ``history``
        self.history = np.zeros((timing.observation_delay[1] + 1, n_slots, observation_dim), dtype=np.float32)
        sensing = largest.sensing
        #: the lidar's errors, and the estimates', are drawn (else the lidar and the truth are what the agents read)
        self.lidar_errors = bool(sensing.lidar_noise or sensing.beam_dropout)
        self.localises = sensing.localises
        #: the motors apply something else than the actions sent
        self.acts = not largest.acting.is_ideal or self.late

    def seed(self, team: int, seed: int) -> None:
        """Seed a team's generator from its scenario seed (:func:`stream`)."""
        self.generators[team] = stream(seed)

    def reset(self, team: int, rows: slice) -> None:
        """Draw a team's episode: its level (when randomised), every agent's gains and delays, the biases' start (from
        their stationary law); forget the actions sent."""
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

    # Sensing --------------------------------------------------------------------------------------------------------

    def sense(self, positions: np.ndarray, velocities: np.ndarray, teams: list[int], drift: bool) -> SensedTeams:
        """What the agents of ``teams`` sense of the true ``positions`` and ``velocities`` (every agent's rows):
        each agent's estimates (white error plus drifting bias; the velocity read in the frame its heading error turns)
        and its lidar's errors.

        :param drift: move the drifting biases on by a step first (not at a reset, whose biases were just drawn)
        """
        config, n_slots = self.config, len(positions)
        sensed_positions, sensed_velocities = positions.copy(), velocities.copy()
        heading_errors = np.zeros(n_slots if self.localises else 0)
        beam_noise = np.zeros((n_slots, config.lidar_rays) if self.lidar_errors else (0, 0))
        dropped = np.zeros(beam_noise.shape, dtype=bool)
        for team in teams:
            rows, generator, sensing = self._rows(team), self.generators[team], self.episodes[team].sensing
            n = rows.stop - rows.start
            if self.localises:
                keep = drift_correlation(sensing.drift_time, config.dt)
                fresh = math.sqrt(1.0 - keep * keep)
                heading_drift, heading_noise = math.radians(sensing.heading_drift_deg), math.radians(sensing.heading_noise_deg)
                if drift and sensing.position_drift:
                    step = generator.normal(0.0, sensing.position_drift, size=(n, 2))
                    self.position_biases[rows] = keep * self.position_biases[rows] + fresh * step
                if drift and heading_drift:
                    step = generator.normal(0.0, heading_drift, size=n)
                    self.heading_biases[rows] = keep * self.heading_biases[rows] + fresh * step
                white = generator.normal(0.0, sensing.position_noise, size=(n, 2)) if sensing.position_noise else 0.0
                sensed_positions[rows] += self.position_biases[rows] + white
                white = generator.normal(0.0, heading_noise, size=n) if heading_noise else 0.0
                errors = heading_errors[rows] = self.heading_biases[rows] + white
                cos, sin, v = np.cos(errors), np.sin(errors), velocities[rows]
                turned = np.stack([cos * v[:, 0] - sin * v[:, 1], sin * v[:, 0] + cos * v[:, 1]], axis=1)
                white = generator.normal(0.0, sensing.velocity_noise, size=(n, 2)) if sensing.velocity_noise else 0.0
                sensed_velocities[rows] = turned + white
            if self.lidar_errors:
                if sensing.lidar_noise:
                    share = sensing.lidar_noise / config.lidar_range
                    beam_noise[rows] = generator.normal(0.0, share, size=(n, config.lidar_rays))
                if sensing.beam_dropout:
                    dropped[rows] = generator.random((n, config.lidar_rays)) < sensing.beam_dropout
        return SensedTeams(sensed_positions, sensed_velocities, heading_errors, beam_noise, dropped)

    def delay_observations(self, observations: np.ndarray, teams: list[int], step_counts: np.ndarray) -> None:
        """Replace, in place, the rows of ``teams`` in this step's ``observations`` by those of each agent's
        observation delay before (the reset's while the episode is younger), remembering this step's.

        :param step_counts: every team's steps since its reset, this step counted
        """
        memory = len(self.history)
        if memory == 1:
            return
        for team in teams:
            rows, now = self._rows(team), int(step_counts[team])
            if now == 0:
                self.history[:, rows] = observations[rows]
            else:
                self.history[now % memory, rows] = observations[rows]
            observations[rows] = self.history[(now - self.observation_delays[rows]) % memory, np.arange(rows.start, rows.stop)]

    def _rows(self, team: int) -> slice:
        return slice(int(self.starts[team]), int(self.starts[team + 1]))

    # Acting ---------------------------------------------------------------------------------------------------------

    def act(
        self, actions: np.ndarray, teams: list[int], step_counts: np.ndarray
    ) -> tuple[np.ndarray, dict[int, ActionSchedule] | None]:
        """The actions the motors apply in the stepped ``teams``: sent ``actions`` (every agent's row) times the gains
        plus the step's force noise, and with delays each team's :class:`ActionSchedule`.

        :param step_counts: every team's steps since its reset, before this step (the time the actions are sent)
        :return: the applied actions (rows of teams not stepped: as sent) and the schedules (``None`` without delays)
        """
        applied = np.array(actions, dtype=np.float64)
        noises: dict[int, np.ndarray | float] = {}
        for team in teams:
            rows, episode = slice(int(self.starts[team]), int(self.starts[team + 1])), self.episodes[team]
            noise = episode.acting.force_noise
            noises[team] = self.generators[team].normal(0.0, noise, size=(rows.stop - rows.start, 2)) if noise else 0.0
            if self.late:
                jitter = episode.timing.jitter
                extra = self.generators[team].uniform(0.0, jitter, size=rows.stop - rows.start) if jitter else 0.0
                now = int(step_counts[team])
                slot = now % self.memory
                self.sent_steps[slot, rows], self.sent[slot, rows] = now, actions[rows]
                self.arrivals[slot, rows] = now + self.action_delays[rows] + extra
        if not self.late:
            for team in teams:
                rows = slice(int(self.starts[team]), int(self.starts[team + 1]))
                applied[rows] = self._motor(applied[rows], rows, noises[team])
            return applied, None
        schedules = {}
        for team in teams:
            rows = slice(int(self.starts[team]), int(self.starts[team + 1]))
            lengths, slots, begins, holds = arrival_parts(
                float(step_counts[team]), self.sent_steps[:, rows], self.arrivals[:, rows]
            )
            sent = np.concatenate([self.sent[:, rows], np.zeros((1, rows.stop - rows.start, 2))])  # slot -1: nothing yet
            held = sent[slots, np.arange(rows.stop - rows.start)]
            schedules[team] = ActionSchedule(lengths, self._motor(held, rows, noises[team]), begins, holds)
        return applied, schedules

    def _motor(self, actions: np.ndarray, rows: slice, noise: np.ndarray | float) -> np.ndarray:
        """What the motors of agents ``rows`` make of ``actions`` (``(..., n, 2)``): the gains (a unicycle's turn gain
        on the turn), plus ``noise``."""
        turn_gains = self.turn_gains[rows] if self.config.dynamics == "unicycle" else self.gains[rows]
        gains = np.stack([self.gains[rows], turn_gains], axis=-1)
        motor: np.ndarray = actions * gains + noise
        return motor


@numba.njit(cache=True)
def arrival_parts(
    now: float, sent_steps: np.ndarray, arrivals: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """The parts of the step from ``now`` to ``now + 1`` (steps) that the arrivals of a team's actions cut, and the
    action each agent applies in each: the newest sent of those arrived (``-1``: none yet).

    :param sent_steps: ``(memory, n)`` the step each remembered action was sent (-1: none)
    :param arrivals: ``(memory, n)`` its arrival time (steps)
    :return: the parts' lengths ``(parts,)`` (shares of the step), the slot of the action each agent applies in each
        part ``(parts, n)`` (-1: none), whether it begins with the part ``(parts, n)``, and for how much of the step it
        holds ``(parts, n)``
    """
    memory, n = sent_steps.shape
    changes = np.full((n, memory + 1), 2.0)  # the times (shares of the step) at which each agent's action changes
    slots = np.full((n, memory + 1), -1, dtype=np.int64)
    counts = np.zeros(n, dtype=np.int64)
    for agent in range(n):
        newest, slot = -1, -1
        for k in range(memory):
            if sent_steps[k, agent] > newest and arrivals[k, agent] <= now:
                newest, slot = sent_steps[k, agent], k
        changes[agent, 0], slots[agent, 0], count = 0.0, slot, 1
        while True:  # later arrivals within the step, earliest first (of simultaneous ones the newest), each newer
            best, best_time = -1, now + 1.0
            for k in range(memory):
                if sent_steps[k, agent] <= newest or not now < arrivals[k, agent] <= best_time:
                    continue
                if arrivals[k, agent] < best_time or (best >= 0 and sent_steps[k, agent] > sent_steps[best, agent]):
                    best, best_time = k, arrivals[k, agent]
            if best < 0:
                break
            newest = sent_steps[best, agent]
            changes[agent, count], slots[agent, count] = best_time - now, best
            count += 1
        counts[agent] = count
    flat = changes.ravel()
    times = np.unique(flat[flat < 1.5])
    parts = len(times)
    lengths = np.empty(parts)
    for part in range(parts):
        lengths[part] = (times[part + 1] if part + 1 < parts else 1.0) - times[part]
    applied = np.full((parts, n), -1, dtype=np.int64)
    begins = np.zeros((parts, n), dtype=np.bool_)
    holds = np.zeros((parts, n))
    for agent in range(n):
        change = 0
        for part in range(parts):
            if change + 1 < counts[agent] and changes[agent, change + 1] <= times[part]:
                change += 1
            applied[part, agent] = slots[agent, change]
            if changes[agent, change] == times[part]:
                begins[part, agent] = True
                end = changes[agent, change + 1] if change + 1 < counts[agent] else 1.0
                holds[part, agent] = end - times[part]
    return lengths, applied, begins, holds


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

    def deliver(self, sent: np.ndarray) -> np.ndarray:
        """What every row receives at this step from its ring neighbours, ``(rows, 2, M)``, given the messages
        ``(rows, M)`` that every row sent at its last step."""
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
        senders = self.senders
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
