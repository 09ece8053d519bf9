"""Disturbances (:mod:`sb3_formation.env.disturbances`, :mod:`sb3_formation.env.disturbed`): each model's statistics
against its setting, delays seen exactly as late as set (a part of a step included), observations consistent with the
positions the agents sensed, seeding, validation, lossy message links, and a unicycle run of the harsh profile.

A standard deviation is measured over 10^5 samples and must lie within 5 % of its setting (sampling alone leaves about
0.2 %); a rate must lie within its binomial 99.9 % interval. Physics is compared with hand-computed values: with
F_max = m v_max / dt (the thesis's default) a full action changes a velocity by v_max = 0.05 m/s in a step.
"""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sb3_formation.controllers.base import AgentStep, Policy
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.disturbances import (
    PROFILES,
    PROFILES_FOLDER,
    Acting,
    Communication,
    Disturbances,
    Failures,
    Sensing,
    Timing,
    load_disturbances,
    profile,
)
from sb3_formation.env.disturbed import Disturber, MessageChannel, arrival_changes
from sb3_formation.env.engine import EngineStep, FormationEngine
from sb3_formation.env.observations import observation_fields, observation_layout
from sb3_formation.env.scenarios import Scenario

TASK = FormationConfig.task("ch5-bearing", stage=3)  # n = 6, beta_ref = 120 deg
SMALL = FormationConfig.task("ch4-individual", stage=3)  # n = 3
V_MAX, DT = 0.05, 0.3
PUSH = 0.05  # m/s: F_max dt / m = (1 kg * 0.05 m/s / 0.3 s) * 0.3 s / 1 kg, the velocity change of a full action
#: three agents far from each other, from the walls and from the goal (no obstacles): nothing touches for many steps
FAR = np.array([[3.0, 3.0], [7.5, 5.0], [12.0, 7.0]])
FAR_GOAL = np.array([7.5, 1.0])
Z_999 = 3.2905  # the two-sided 99.9 % quantile of the normal law
STD_TOLERANCE = 0.05
SAMPLES = 100_000


# Helpers --------------------------------------------------------------------------------------------------------------


def make_engine(config: FormationConfig, disturbances: Any = None, teams: int = 1, seed: int = 0) -> FormationEngine:
    """An engine of ``teams`` teams of ``config`` (with ``disturbances`` if given), each reset with seed ``seed + team``."""
    if disturbances is not None:
        config = config.replace(disturbances=disturbances)
    engine = FormationEngine([config] * teams)
    for team in range(teams):
        engine.reset(team, seed=seed + team)
    return engine


def far_engine(disturbances: Any, seed: int = 0, **overrides: Any) -> FormationEngine:
    """One team of three agents placed by hand far from everything (:data:`FAR`)."""
    engine = FormationEngine([SMALL.replace(disturbances=disturbances, **overrides)])
    engine.reset(0, seed=seed, scenario=Scenario(FAR, FAR_GOAL))
    return engine


def layout(config: FormationConfig) -> dict[str, slice]:
    """The observation's field name -> its columns."""
    return observation_layout(observation_fields(config))


def clamp(velocities: np.ndarray) -> np.ndarray:
    """Eq. 19's clamp, by hand: every velocity faster than v_max scaled down to v_max."""
    speeds = np.hypot(velocities[:, 0], velocities[:, 1])[:, None]
    return np.where(speeds > V_MAX, velocities * (V_MAX / np.maximum(speeds, 1e-300)), velocities)


def assert_std(samples: np.ndarray, setting: float, what: str) -> float:
    """Zero mean (within 4 standard errors) and a standard deviation within 5 % of ``setting``; returns it."""
    samples = np.asarray(samples, dtype=np.float64).ravel()
    assert samples.size >= SAMPLES, f"{what}: {samples.size} samples"
    measured = float(samples.std())
    assert abs(measured / setting - 1.0) < STD_TOLERANCE, f"{what}: standard deviation {measured:.6g}, set {setting:.6g}"
    assert abs(samples.mean()) < 4 * setting / math.sqrt(samples.size), f"{what}: mean {samples.mean():.3g}"
    return measured


def assert_rate(hits: int, trials: int, rate: float, what: str) -> None:
    """``hits`` of ``trials`` within the binomial 99.9 % interval of ``rate`` (normal approximation, trials >> 1)."""
    half = Z_999 * math.sqrt(rate * (1.0 - rate) / trials)
    assert abs(hits / trials - rate) <= half, f"{what}: {hits}/{trials} = {hits / trials:.5f}, set {rate} +- {half:.5f}"


def test_hand_constants() -> None:
    """The hand values above are the tasks': F_max = 1/6 N, m = 1 kg, dt = 0.3 s, v_max = 0.05 m/s, n = 3 and 6."""
    for config in (TASK, SMALL):
        assert config.force_max * config.dt / config.agent_mass == pytest.approx(PUSH, rel=1e-12)
        assert (config.v_max, config.dt) == (V_MAX, DT)
    assert (SMALL.n_agents, TASK.n_agents, SMALL.physics_substeps) == (3, 6, 2)


# 1. Each model's statistics ---------------------------------------------------------------------------------------------

#: a lidar that reaches across the world: every beam meets a wall, so every obstacle reading is < 1 and carries noise
FAR_LIDAR = TASK.replace(lidar_range=20.0)


def lidar_runs(disturbances: Disturbances, steps: int = 25, teams: int = 8) -> tuple[list[EngineStep], list[EngineStep]]:
    """The steps of an ideal engine and of one with ``disturbances`` (same seeds, same random actions)."""
    ideal, disturbed = make_engine(FAR_LIDAR, teams=teams, seed=40), make_engine(FAR_LIDAR, disturbances, teams, seed=40)
    actions = np.random.default_rng(1).uniform(-1, 1, (steps, teams * FAR_LIDAR.n_agents, 2))
    return [ideal.step(a) for a in actions], [disturbed.step(a) for a in actions]


def test_lidar_range_noise_has_its_standard_deviation() -> None:
    """Noisy readings minus the ideal engine's readings of the same positions, where the ideal reading is far from the
    clip bounds [0, 1]: Gaussian of 5 cm; a beam that saw nothing (agent channel) still reads 1."""
    noise = 0.05
    ideal_steps, noisy_steps = lidar_runs(Disturbances(sensing=Sensing(lidar_noise=noise)))
    fields = layout(FAR_LIDAR)
    share, errors = noise / FAR_LIDAR.lidar_range, []
    for ideal, noisy in zip(ideal_steps, noisy_steps):
        assert np.array_equal(ideal.positions, noisy.positions) and np.array_equal(ideal.rewards, noisy.rewards)
        clean = ideal.observations[:, fields["lidar_obstacles"]].astype(np.float64)
        read = noisy.observations[:, fields["lidar_obstacles"]].astype(np.float64)
        inside = (clean > 6 * share) & (clean < 1 - 6 * share)
        assert inside.mean() > 0.99
        errors.append((read - clean)[inside] * FAR_LIDAR.lidar_range)
        nothing = ideal.observations[:, fields["lidar_agents"]] == 1.0
        assert nothing.any() and np.all(noisy.observations[:, fields["lidar_agents"]][nothing] == 1.0)
    assert_std(np.concatenate(errors), noise, "lidar range noise (m)")


def test_beam_dropout_rate_lies_in_its_binomial_interval() -> None:
    """A dropped beam reads 1 on both channels; the others read exactly what the ideal lidar reads; the share dropped
    of beams that saw something is 10 % within its 99.9 % interval."""
    rate = 0.1
    ideal_steps, dropping_steps = lidar_runs(Disturbances(sensing=Sensing(beam_dropout=rate)))
    fields = layout(FAR_LIDAR)
    hits = trials = 0
    for ideal, dropping in zip(ideal_steps, dropping_steps):
        clean, read = (step.observations[:, fields["lidar_obstacles"]] for step in (ideal, dropping))
        agents = dropping.observations[:, fields["lidar_agents"]]
        saw = clean < 1.0
        dropped = saw & (read == 1.0)
        assert np.array_equal(read[saw & ~dropped], clean[saw & ~dropped])  # no other change
        assert np.all(agents[dropped] == 1.0)  # nothing seen on either channel
        hits, trials = hits + int(dropped.sum()), trials + int(saw.sum())
    assert trials >= SAMPLES
    assert_rate(hits, trials, rate, "beam dropout")


def test_white_position_and_velocity_noise_have_their_standard_deviations() -> None:
    """Agents at rest: the position an agent observes (goal - goal_offset) minus the truth is Gaussian of 4 cm per axis,
    its observed velocity minus the truth of 4 mm/s; the true world is not touched (the agents stay where they were)."""
    position_noise, velocity_noise = 0.04, 0.004
    sensing = Sensing(position_noise=position_noise, velocity_noise=velocity_noise)
    teams, steps = 16, 521
    engine = make_engine(TASK, Disturbances(sensing=sensing), teams=teams, seed=100)
    fields, goals = layout(TASK), np.repeat(engine.episodes.goals, TASK.n_agents, axis=0)
    start = engine.latest.positions.copy()
    position_errors, velocity_errors = [], []
    for _ in range(steps):
        step = engine.step(np.zeros((teams * TASK.n_agents, 2)))
        observations = step.observations.astype(np.float64)
        position_errors.append(goals - observations[:, fields["goal_offset"]] - step.positions)
        velocity_errors.append(observations[:, fields["velocity"]] - step.velocities)
    assert np.array_equal(step.positions, start) and not step.velocities.any()
    assert_std(np.concatenate(position_errors), position_noise, "position noise (m)")
    assert_std(np.concatenate(velocity_errors), velocity_noise, "velocity noise (m/s)")


def test_drifting_biases_have_their_stationary_deviation_and_step_correlation() -> None:
    """Position and heading biases drawn from their stationary law at the reset stay at it (5 cm, 2 deg) step after
    step, and keep a correlation of exp(-dt / drift_time) = exp(-0.5) over a step (the Gauss-Markov process)."""
    drift, heading_drift_deg, drift_time = 0.05, 2.0, 0.6
    sensing = Sensing(position_drift=drift, heading_drift_deg=heading_drift_deg, drift_time=drift_time)
    config, agents = SMALL.replace(disturbances=Disturbances(sensing=sensing)), SAMPLES
    disturber = Disturber(config, np.array([0, agents]), observation_dim=1)
    disturber.seed(0, 5)
    disturber.reset(0, slice(0, agents))
    zeros = np.zeros((agents, 2))
    sensed = [disturber.sense(zeros, zeros, [0], drift=step > 0) for step in range(12)]
    for index in (0, 1, 11):  # the reset's draw, and later steps
        assert_std(sensed[index].positions, drift, f"position bias at step {index} (m)")
        assert_std(sensed[index].heading_errors, math.radians(heading_drift_deg), f"heading bias at step {index} (rad)")
    keep = math.exp(-DT / drift_time)
    for before, after in itertools.pairwise(sensed):
        correlation = np.corrcoef(before.positions.ravel(), after.positions.ravel())[0, 1]
        assert abs(correlation - keep) < 0.01, (correlation, keep)  # its standard error is about 0.002
        correlation = np.corrcoef(before.heading_errors, after.heading_errors)[0, 1]
        assert abs(correlation - keep) < 0.01, (correlation, keep)


def test_heading_noise_turns_the_velocity_estimate() -> None:
    """A heading error e (Gaussian of 3 deg) turns the velocity an agent reads by e; velocity noise of 4 mm/s is added
    after the turn (the Disturber directly, 10^5 agents with random velocities)."""
    sensing = Sensing(heading_noise_deg=3.0, velocity_noise=0.004)
    config, agents = SMALL.replace(disturbances=Disturbances(sensing=sensing)), SAMPLES
    disturber = Disturber(config, np.array([0, agents]), observation_dim=1)
    disturber.seed(0, 6)
    disturber.reset(0, slice(0, agents))
    velocities = np.random.default_rng(2).uniform(-V_MAX, V_MAX, (agents, 2))
    positions = np.random.default_rng(3).uniform(0, 10, (agents, 2))
    sensed = disturber.sense(positions, velocities, [0], drift=True)
    assert np.array_equal(sensed.positions, positions)  # no position error set
    errors = sensed.heading_errors
    assert_std(errors, math.radians(3.0), "heading noise (rad)")
    turned = np.stack(
        [
            np.cos(errors) * velocities[:, 0] - np.sin(errors) * velocities[:, 1],
            np.sin(errors) * velocities[:, 0] + np.cos(errors) * velocities[:, 1],
        ],
        axis=1,
    )
    assert_std(sensed.velocities - turned, 0.004, "velocity noise after the turn (m/s)")


def test_a_heading_error_turns_the_lidar_rays_and_the_velocity_the_agent_reads() -> None:
    """A heading error of +8 degrees (two rays' spacing, held by a bias that practically does not drift): the agent
    reads at ray k what the ideal lidar reads at ray k - 2 (it takes directions 8 degrees clockwise of the ones it
    thinks), and its velocity turned by +8 degrees; its position is not touched."""
    sensing = Sensing(heading_drift_deg=1e-6, drift_time=86_400.0)
    ideal = make_engine(FAR_LIDAR, teams=2, seed=45)
    turned = make_engine(FAR_LIDAR, Disturbances(sensing=sensing), teams=2, seed=45)
    error = math.radians(8.0)
    turned.disturber.heading_biases[:] = error  # type: ignore[union-attr]
    fields = layout(FAR_LIDAR)
    for action in np.random.default_rng(13).uniform(-1, 1, (3, 2 * FAR_LIDAR.n_agents, 2)):
        a, b = ideal.step(action), turned.step(action)
        assert np.array_equal(a.positions, b.positions)
        for name in ("lidar_obstacles", "lidar_agents"):
            shifted = np.roll(a.observations[:, fields[name]], 2, axis=1)  # column k holds ideal reading k - 2
            assert b.observations[:, fields[name]] == pytest.approx(shifted, abs=1e-5), name
        v = a.velocities
        rotation = np.stack(
            [math.cos(error) * v[:, 0] - math.sin(error) * v[:, 1], math.sin(error) * v[:, 0] + math.cos(error) * v[:, 1]],
            axis=1,
        )
        assert b.observations[:, fields["velocity"]] == pytest.approx(rotation, abs=1e-7)
        assert b.observations[:, fields["goal_offset"]] == pytest.approx(a.observations[:, fields["goal_offset"]], abs=1e-6)


def test_motor_gains_are_uniform_in_their_interval() -> None:
    """10^5 agents' gains, drawn from [0.8, 1.2]: within it, mean 1 and standard deviation 0.4 / sqrt(12)."""
    config = SMALL.replace(disturbances=Disturbances(acting=Acting(gain=(0.8, 1.2))))
    disturber = Disturber(config, np.array([0, SAMPLES]), observation_dim=1)
    disturber.seed(0, 7)
    disturber.reset(0, slice(0, SAMPLES))
    gains = disturber.gains
    assert gains.min() >= 0.8 and gains.max() <= 1.2
    assert abs(gains.mean() - 1.0) < 4 * 0.4 / math.sqrt(12 * SAMPLES)
    assert abs(gains.std() / (0.4 / math.sqrt(12)) - 1.0) < STD_TOLERANCE


def test_the_motor_gain_is_drawn_once_per_episode_and_scales_the_velocity_change() -> None:
    """Free holonomic agents: the velocity change of action a is gain * a * F_max * dt / m, the same gain at every step
    of an episode, clamped to v_max when it would exceed it; the next reset draws new gains."""
    engine = far_engine(Disturbances(acting=Acting(gain=(0.8, 1.2))), seed=3)

    def measure(action: tuple[float, float], before: np.ndarray, positions: np.ndarray) -> np.ndarray:
        step = engine.step(np.tile(action, (3, 1)))
        change = step.velocities - before
        gains = change / (np.array(action) * PUSH)
        assert gains[:, 0] == pytest.approx(gains[:, 1], abs=1e-9)  # one gain on both axes
        assert step.positions == pytest.approx(positions + DT * step.velocities, abs=1e-12)  # v first, then p
        return gains[:, 0]

    first = measure((0.5, -0.25), np.zeros((3, 2)), FAR)
    velocities, positions = engine.latest.velocities.copy(), engine.latest.positions.copy()
    second = measure((-0.25, 0.5), velocities, positions)
    assert second == pytest.approx(first, abs=1e-9)  # drawn once per episode
    assert np.all((first >= 0.8) & (first <= 1.2)) and np.abs(first - 1.0).min() > 1e-3
    assert first == pytest.approx(engine.disturber.gains, abs=1e-9)  # type: ignore[union-attr]
    # now v = g (0.25, 0.25) v_max; a full (1, 1) would add g (1, 1) v_max: |v| = 1.25 sqrt(2) g v_max > v_max, clamped
    step = engine.step(np.ones((3, 2)))
    assert step.velocities == pytest.approx(np.full((3, 2), V_MAX / math.sqrt(2)), abs=1e-15)
    engine.reset(0, scenario=Scenario(FAR, FAR_GOAL))  # the next episode, its generator going on
    again = measure((0.5, -0.25), np.zeros((3, 2)), FAR)
    assert np.all((again >= 0.8) & (again <= 1.2)) and np.abs(again - first).min() > 1e-6


def test_force_noise_has_its_standard_deviation() -> None:
    """Each step's action cancels the agent's velocity, so its velocity after the step is the force noise's alone:
    (v' - v) / (F_max dt / m) - a is Gaussian of 0.1 (a share of F_max) per axis, and never reaches the clamp."""
    noise, teams, steps = 0.1, 16, 521
    engine = make_engine(TASK, Disturbances(acting=Acting(force_noise=noise)), teams=teams, seed=200)
    velocities, samples = np.zeros((teams * TASK.n_agents, 2)), []
    for _ in range(steps):
        actions = np.clip(-velocities / PUSH, -1.0, 1.0)
        step = engine.step(actions)
        assert np.hypot(step.velocities[:, 0], step.velocities[:, 1]).max() < V_MAX  # the clamp never acts
        free = step.contacts.sum(axis=1) == 0
        samples.append(((step.velocities - velocities) / PUSH - actions)[free])
        velocities = step.velocities
    samples_array = np.concatenate(samples)
    assert len(samples_array) > 0.99 * steps * teams * TASK.n_agents
    assert_std(samples_array, noise, "force noise (share of F_max)")


# 2. Delays ------------------------------------------------------------------------------------------------------------


def test_an_observation_delay_shows_each_agent_the_observation_of_its_delay_before() -> None:
    """Observation delays drawn from [0, 3] whole steps: row i at step t is the ideal engine's row i at step t - k_i
    (the reset's before), bit for bit; each k_i, found from the rows alone, is the one drawn, and they differ."""
    teams, steps = 2, 12
    ideal = make_engine(TASK, teams=teams, seed=21)
    late = make_engine(TASK, Disturbances(timing=Timing(observation_delay=(0, 3))), teams=teams, seed=21)
    ideal_rows, late_rows = [ideal.latest.observations.copy()], [late.latest.observations.copy()]
    actions = np.random.default_rng(4).uniform(-1, 1, (steps, teams * TASK.n_agents, 2))
    for action in actions:
        a, b = ideal.step(action), late.step(action)
        assert np.array_equal(a.positions, b.positions) and np.array_equal(a.rewards, b.rewards)
        ideal_rows.append(a.observations)
        late_rows.append(b.observations)
    found = []
    for row in range(teams * TASK.n_agents):
        fits = [
            k
            for k in range(6)
            if all(np.array_equal(late_rows[t][row], ideal_rows[max(t - k, 0)][row]) for t in range(steps + 1))
        ]
        assert len(fits) == 1, (row, fits)
        found.extend(fits)
    assert found == late.disturber.observation_delays.tolist()  # type: ignore[union-attr]
    assert set(found) <= {0, 1, 2, 3} and len(set(found)) >= 2


def test_an_action_delay_of_whole_steps_moves_the_world_as_the_ideal_one_under_the_shifted_actions() -> None:
    """A delay of 2 steps: the world moves as the ideal world under the actions shifted by 2, zeros first (random
    scenes; every agent pushes towards its team's centroid, so the agents meet and press on each other)."""
    teams, steps, k = 2, 60, 2
    ideal = make_engine(TASK, teams=teams, seed=31)
    late = make_engine(TASK, Disturbances(timing=Timing(action_delay=(2.0, 2.0))), teams=teams, seed=31)
    start = ideal.latest.positions
    inward = np.repeat(start.reshape(teams, TASK.n_agents, 2).mean(axis=1), TASK.n_agents, axis=0) - start
    inward /= np.hypot(inward[:, 0], inward[:, 1])[:, None]
    actions = np.clip(inward + np.random.default_rng(5).uniform(-0.3, 0.3, (steps, *inward.shape)), -1, 1)
    contacts = 0
    for t in range(steps):
        shifted = actions[t - k] if t >= k else np.zeros_like(actions[0])
        a, b = ideal.step(shifted), late.step(actions[t])
        assert b.positions == pytest.approx(a.positions, abs=1e-9), t
        assert b.velocities == pytest.approx(a.velocities, abs=1e-9), t
        assert np.array_equal(a.contacts, b.contacts)
        contacts += int(a.contacts.sum())
    assert contacts > 100


def piecewise_motion(actions: np.ndarray, delay: float) -> tuple[list[np.ndarray], list[np.ndarray], bool]:
    """By hand: agents from rest at :data:`FAR` under actions sent each step and arriving ``delay`` = k + f steps late.
    In step s the action sent at s - k - 1 holds for the first f of the step (zero force before the first action),
    then the one sent at s - k: velocity v0 + a_prev F_max f dt / m, clamped, then + a_new F_max (1 - f) dt / m,
    clamped; the position moves at each velocity for its share of the step.

    :return: positions and velocities after every step, and whether the clamp acted
    """
    whole = math.floor(delay)
    part = delay - whole

    def sent(step: int) -> np.ndarray:
        return actions[step] if 0 <= step < len(actions) else np.zeros_like(actions[0])

    positions, velocities, clamped = FAR.copy(), np.zeros_like(FAR), False
    all_positions, all_velocities = [], []
    for step in range(len(actions)):
        first = clamp(velocities + sent(step - whole - 1) * PUSH * part)
        raw = first + sent(step - whole) * PUSH * (1 - part)
        then = clamp(raw)
        clamped = clamped or not np.array_equal(raw, then)
        positions = positions + DT * (part * first + (1 - part) * then)
        velocities = then
        all_positions.append(positions)
        all_velocities.append(velocities)
    return all_positions, all_velocities, clamped


@pytest.mark.parametrize(("delay", "substeps"), [(0.4, 2), (0.75, 2), (1.75, 2), (0.6, 3)])
def test_a_part_step_action_delay_applies_the_previous_action_for_that_part(delay: float, substeps: int) -> None:
    """Three free holonomic agents, 12 steps of random actions (two of them full, so that the clamp acts): positions and
    velocities after every step are those of the hand-computed piecewise motion (:func:`piecewise_motion`), whether
    the part boundary falls in the last Pymunk sub-step (0.75 of a step with 2 sub-steps) or not."""
    actions = np.random.default_rng(6).uniform(-1, 1, (12, 3, 2))
    actions[3:5] = 1.0
    engine = far_engine(Disturbances(timing=Timing(action_delay=(delay, delay))), physics_substeps=substeps)
    positions, velocities, clamped = piecewise_motion(actions, delay)
    assert clamped
    for t, action in enumerate(actions):
        step = engine.step(action)
        assert not step.contacts.any()
        assert step.positions == pytest.approx(positions[t], abs=1e-9), t
        assert step.velocities == pytest.approx(velocities[t], abs=1e-12), t


def test_a_part_step_action_delay_carries_a_unicycles_last_forward_speed() -> None:
    """Unicycles driving straight (turn action 0) under a delay of 0.75 steps: the forward speed after each step is
    the hand-computed one of the second part (v0 + a_prev F_max 0.75 dt / m, clipped, then + a_new F_max 0.25 dt / m,
    clipped to +-v_max), and headings do not change."""
    delay, headings = 0.75, np.array([0.0, 1.0, 2.0])
    config = SMALL.replace(dynamics="unicycle", disturbances=Disturbances(timing=Timing(action_delay=(delay, delay))))
    engine = FormationEngine([config])
    engine.reset(0, seed=0, scenario=Scenario(FAR, FAR_GOAL, headings=headings))
    actions = np.random.default_rng(7).uniform(-1, 1, (12, 3, 2))
    actions[..., 1], actions[3:5, :, 0] = 0.0, 1.0
    speeds = np.zeros(3)
    for t, action in enumerate(actions):
        engine.step(action)
        previous = actions[t - 1, :, 0] if t >= 1 else np.zeros(3)
        first = np.clip(speeds + previous * PUSH * delay, -V_MAX, V_MAX)
        speeds = np.clip(first + action[:, 0] * PUSH * (1 - delay), -V_MAX, V_MAX)
        assert engine.dynamics.forward_speeds == pytest.approx(speeds, abs=1e-12), t  # type: ignore[attr-defined]
    assert engine.worlds[0].headings == pytest.approx(headings, abs=1e-12)  # type: ignore[union-attr]


def changes(now: float, sent: list[list[int]], arrivals: list[list[float]]) -> list[list[tuple[float, int]]]:
    """Each agent's changes of action within the step from ``now``: (time, slot) pairs."""
    sent_steps, arrival_times = np.array(sent, dtype=np.int64), np.array(arrivals, dtype=np.float64)
    times, slots, counts = arrival_changes(np.full(sent_steps.shape[1], now), sent_steps, arrival_times)
    return [[(round(float(times[a, c]), 12), int(slots[a, c])) for c in range(counts[a])] for a in range(len(counts))]


def test_arrival_changes_happen_at_arrivals_and_the_newest_sent_holds() -> None:
    """Hand-built rings of sent actions (rows: memory slots, columns: agents) at step 7."""
    inf = math.inf
    # agent 0: sent 5 has arrived; sent 7 arrives at 7.3, sent 6 (older) at 7.9 after it: 6 never applies.
    # agent 1: sent 5 has arrived; sent 6 arrives at 7.2, sent 7 at 7.6.
    found = changes(7.0, [[5, 5], [6, 6], [7, 7], [-1, -1]], [[5.2, 6.5], [7.9, 7.2], [7.3, 7.6], [inf, inf]])
    assert found == [[(0.0, 0), (0.3, 2)], [(0.0, 0), (0.2, 1), (0.6, 2)]]
    # arrived before the step out of order (sent 6 at 6.5, sent 5 at 6.9): the newest sent, 6, holds the whole step
    assert changes(7.0, [[6], [5], [-1]], [[6.5], [6.9], [inf]]) == [[(0.0, 0)]]
    # nothing arrived yet: no action (slot -1, zero force) until sent 0 arrives at 0.5
    assert changes(0.0, [[0], [-1]], [[0.5], [inf]]) == [[(0.0, -1), (0.5, 0)]]
    # an arrival at the step's end belongs to the next step
    assert changes(7.0, [[6], [7]], [[6.0], [8.0]]) == [[(0.0, 0)]]
    assert changes(8.0, [[6], [7]], [[6.0], [8.0]]) == [[(0.0, 1)]]
    # two arrivals at once (sent 6 and 7 both at 7.5), in either order of the slots: the newest, 7, holds from there
    for order in ([0, 1, 2], [2, 1, 0], [0, 2, 1]):
        sent, arrivals = np.array([[5], [6], [7]])[order], np.array([[5.2], [7.5], [7.5]])[order]
        found = changes(7.0, sent.tolist(), arrivals.tolist())
        assert [(time, int(sent[slot, 0])) for time, slot in found[0]] == [(0.0, 5), (0.5, 7)], order


# 3. Observation consistency ---------------------------------------------------------------------------------------------


def hand_rows(sensed: np.ndarray, goal: np.ndarray, config: FormationConfig) -> dict[str, np.ndarray]:
    """A team's rows' formation fields by hand (``docs/design.md``) from its agents' sensed positions ``(n, 2)``:
    neighbours i - 1 and i + 1, offsets p_j - p_i, the centroid, beta_i anti-clockwise from the bearing to the
    succeeding neighbour to the bearing to the preceding one, angle error beta_ref - beta."""
    n = len(sensed)
    preceding, succeeding = (np.arange(n) - 1) % n, (np.arange(n) + 1) % n
    to_preceding, to_succeeding = sensed[preceding] - sensed, sensed[succeeding] - sensed
    distances = np.stack([np.hypot(*to_preceding.T), np.hypot(*to_succeeding.T)], axis=1)
    centroid = sensed.mean(axis=0)
    centroid_distances = np.hypot(*(sensed - centroid).T)
    beta = np.degrees(
        np.arctan2(to_preceding[:, 1], to_preceding[:, 0]) - np.arctan2(to_succeeding[:, 1], to_succeeding[:, 0])
    )
    beta = np.mod(beta, 360.0)
    beta_ref = (n - 2) * 180.0 / n
    return {
        "neighbour_offsets": np.concatenate([to_preceding, to_succeeding], axis=1),
        "neighbour_distances": distances,
        "centroid_distance": centroid_distances[:, None],
        "neighbour_distance_errors": distances - config.d_ref,
        "centroid_distance_error": config.eta_c - centroid_distances[:, None],
        "angle_error": beta_ref - beta[:, None],
        "neighbour_angle_errors": np.stack([beta_ref - beta[preceding], beta_ref - beta[succeeding]], axis=1),
        "centroid_goal_offset": np.tile(goal - centroid, (n, 1)),
        "flag_orientation": ((beta > 0) & (beta < 180)).astype(float)[:, None],
        "flag_range": np.full((n, 1), float(np.all(distances <= config.d_ref))),
    }


#: absolute tolerances of the float32 observation against the hand values from float32 goal offsets (m, m/s, deg)
TOLERANCES = {"angle_error": 2e-3, "neighbour_angle_errors": 2e-3}

LOCALISATION = Sensing(position_noise=0.05, position_drift=0.05, heading_noise_deg=3.0, velocity_noise=0.005)


def test_with_localisation_noise_each_row_is_the_geometry_of_the_sensed_positions() -> None:
    """Localisation noise only (position white noise and drift, heading and velocity noise): from the sensed positions
    (goal - goal_offset of each row), every row's neighbour offsets, distances, centroid distance, their errors, angle
    errors, flags and centroid goal offset are the hand-computed ones, and relative velocities are the differences of
    the rows' velocities; the sensed positions are off the truth by about sqrt(0.05^2 + 0.05^2) per axis. Rewards and
    the world stay the ideal engine's."""
    teams = 2
    ideal = make_engine(TASK, teams=teams, seed=51)
    noisy = make_engine(TASK, Disturbances(sensing=LOCALISATION), teams=teams, seed=51)
    fields, n = layout(TASK), TASK.n_agents
    observations, positions = [noisy.latest.observations.copy()], [noisy.latest.positions.copy()]
    actions = np.random.default_rng(8).uniform(-1, 1, (8, teams * n, 2))
    for action in actions:
        a, b = ideal.step(action), noisy.step(action)
        assert np.array_equal(a.positions, b.positions) and np.array_equal(a.rewards, b.rewards)
        assert np.array_equal(a.info_values, b.info_values)
        observations.append(b.observations)
        positions.append(b.positions)
    errors = []
    for rows, truth in zip(observations, positions):
        rows = rows.astype(np.float64)
        for team in range(teams):
            team_rows, goal = slice(team * n, (team + 1) * n), noisy.episodes.goals[team]
            sensed = goal - rows[team_rows, fields["goal_offset"]]
            errors.append(sensed - truth[team_rows])
            for name, expected in hand_rows(sensed, goal, TASK).items():
                assert rows[team_rows, fields[name]] == pytest.approx(expected, abs=TOLERANCES.get(name, 1e-5)), name
            velocities = rows[team_rows, fields["velocity"]]
            relative = np.concatenate([np.roll(velocities, 1, axis=0), np.roll(velocities, -1, axis=0)], axis=1)
            expected_relative = relative - np.tile(velocities, 2)
            assert rows[team_rows, fields["neighbour_relative_velocities"]] == pytest.approx(expected_relative, abs=1e-7)
    spread = float(np.concatenate(errors).std())
    assert 0.5 * math.hypot(0.05, 0.05) < spread < 1.5 * math.hypot(0.05, 0.05), spread


def test_the_centroid_goal_offset_change_is_the_change_of_what_the_agent_observed() -> None:
    """With localisation noise, centroid_goal_offset_change (c_g,t - c_g,t-1) is the difference of the centroid goal
    offsets the row observed at t and at t - 1 (as an agent on board computes it), not one that needs the truth."""
    noisy = make_engine(TASK, Disturbances(sensing=LOCALISATION), seed=52)
    fields = layout(TASK)
    before = noisy.latest.observations[:, fields["centroid_goal_offset"]].astype(np.float64)
    for action in np.random.default_rng(9).uniform(-1, 1, (4, TASK.n_agents, 2)):
        rows = noisy.step(action).observations.astype(np.float64)
        now = rows[:, fields["centroid_goal_offset"]]
        assert rows[:, fields["centroid_goal_offset_change"]] == pytest.approx(now - before, abs=1e-5)
        before = now


# 4. Seeding and the ideal world -----------------------------------------------------------------------------------------


def harsh_episode(seed: int, scenarios: list[Scenario] | None = None) -> tuple[dict[str, np.ndarray], list[Scenario]]:
    """50 steps of two teams of the harsh profile, reset with ``seed`` (and ``scenarios`` if given), fixed actions:
    the observations, rewards and positions (the reset's first), the motor gains, and the scenarios played."""
    engine = FormationEngine([TASK.replace(disturbances="harsh")] * 2)
    observations = [
        engine.reset(team, seed=seed + team, scenario=None if scenarios is None else scenarios[team]) for team in range(2)
    ]
    record: dict[str, list[np.ndarray]] = {
        "observations": [np.concatenate(observations)],
        "rewards": [],
        "positions": [engine.latest.positions.copy()],
    }
    for action in np.random.default_rng(10).uniform(-1, 1, (50, 2 * TASK.n_agents, 2)):
        step = engine.step(action)
        record["observations"].append(step.observations)
        record["rewards"].append(step.rewards)
        record["positions"].append(step.positions)
    result = {name: np.stack(values) for name, values in record.items()}
    result["gains"] = engine.disturber.gains.copy()  # type: ignore[union-attr]
    return result, [scenario for scenario in engine.scenarios if scenario is not None]


def test_the_same_seed_gives_the_same_noisy_episode_and_another_seed_other_noise() -> None:
    """Harsh profile, 50 steps: the same seed gives the same observations, rewards, positions and gains bit for bit;
    another seed on the same scenes gives other gains, other observations and another path."""
    first, scenarios = harsh_episode(3)
    second, _ = harsh_episode(3)
    for name in first:
        assert np.array_equal(first[name], second[name]), name
    other, _ = harsh_episode(1003, scenarios)  # the same scenes, another seed: other noise
    assert np.array_equal(other["positions"][0], first["positions"][0])
    assert np.all(other["gains"] != first["gains"])
    goal_offsets = layout(TASK)["goal_offset"]  # noisy position estimates in every row
    assert np.all(other["observations"][..., goal_offsets] != first["observations"][..., goal_offsets])
    assert np.abs(other["positions"][-1] - first["positions"][-1]).max() > 1e-3


def test_ideal_disturbances_leave_the_engine_bit_for_bit() -> None:
    """``ideal`` (by name, as a mapping, as a part scaled to 0, or with only a time constant changed) is the config
    without the field, makes no Disturber, and plays the same episode bit for bit; its ``to_dict`` has no key."""
    assert profile("harsh").scaled(0.0) == Disturbances() == load_disturbances("ideal") == load_disturbances({})
    for disturbances in ("ideal", {}, {"profile": "ideal"}, Disturbances()):
        assert TASK.replace(disturbances=disturbances) == TASK
    assert FormationConfig.task("ch5-bearing", stage=3, disturbances="ideal") == TASK
    assert "disturbances" not in TASK.to_dict() and "disturbances" not in TASK.replace(disturbances="ideal").to_dict()
    slow_drift = TASK.replace(disturbances=Disturbances(sensing=Sensing(drift_time=5.0)))
    assert slow_drift != TASK and slow_drift.disturbances.is_ideal
    runs = []
    for config in (TASK, slow_drift, TASK.replace(disturbances=profile("harsh").scaled(0.0))):
        engine = FormationEngine([config] * 2)
        assert engine.disturber is None
        steps = [np.concatenate([engine.reset(team, seed=60 + team) for team in range(2)])]
        for action in np.random.default_rng(11).uniform(-1, 1, (20, 2 * TASK.n_agents, 2)):
            step = engine.step(action)
            steps.extend([step.observations, step.rewards, step.positions, step.velocities, step.info_values])
        runs.append(steps)
    for run in runs[1:]:
        assert all(np.array_equal(a, b) for a, b in zip(runs[0], run))


def test_a_disturbed_config_round_trips_through_to_dict() -> None:
    """A profile, a randomised one and a file's changes are written by ``to_dict`` and read back by ``from_dict`` (also
    through JSON, where pairs become lists)."""
    edited = {"profile": "realistic", "timing": {"action_delay": [0.5, 0.5]}, "communication": {"loss": 0.2}}
    for disturbances in ("harsh", profile("realistic").randomised(), edited):
        config = TASK.replace(disturbances=disturbances)
        written = config.to_dict()
        assert isinstance(written["disturbances"], dict)
        assert FormationConfig.from_dict(written) == config
        assert FormationConfig.from_dict(json.loads(json.dumps(written))) == config
    read = TASK.replace(disturbances=edited).disturbances
    assert read.timing == Timing(observation_delay=(0, 1), action_delay=(0.5, 0.5), jitter=0.1)
    assert read.communication == Communication(loss=0.2, delay=(0, 1)) and read.sensing == profile("realistic").sensing


def test_profiles_scaling_and_parts_by_hand() -> None:
    """The harsh profile's numbers (its file), scaled by 0.5 and by 2 and 5 by hand, and one part alone."""
    harsh = profile("harsh")
    assert PROFILES == ("ideal", "realistic", "harsh", "failures")
    assert profile("failures") == Disturbances(failures=Failures(probability=0.5, steps=(0, 600)))
    assert harsh == load_disturbances(PROFILES_FOLDER / "harsh.yaml") == load_disturbances(str(PROFILES_FOLDER / "harsh.yaml"))
    assert harsh.sensing == Sensing(0.03, 0.05, 0.06, 0.05, 3.5, 3.5, 0.005, 30.0)
    assert harsh.acting == Acting(gain=(0.75, 1.25), turn_gain=(0.75, 1.25), force_noise=0.1)
    assert harsh.timing == Timing(observation_delay=(0, 2), action_delay=(0.0, 2.5), jitter=0.5)
    assert harsh.communication == Communication(loss=0.3, delay=(0, 2))
    half = harsh.scaled(0.5)
    assert half.sensing.lidar_noise == pytest.approx(0.015) and half.sensing.beam_dropout == pytest.approx(0.025)
    assert half.sensing.drift_time == 30.0  # a time constant is kept
    assert half.acting.gain == pytest.approx((0.875, 1.125)) and half.acting.force_noise == pytest.approx(0.05)
    assert half.timing.observation_delay == (0, 1) and half.timing.action_delay == pytest.approx((0.0, 1.25))
    assert half.communication.loss == pytest.approx(0.15) and half.communication.delay == (0, 1)
    double = harsh.scaled(2.0)
    assert double.acting.gain == pytest.approx((0.5, 1.5)) and double.timing.observation_delay == (0, 4)
    assert double.communication.loss == pytest.approx(0.6) and double.timing.jitter == pytest.approx(1.0)
    five = harsh.scaled(5.0)
    assert five.communication.loss == 1.0 and five.acting.gain == pytest.approx((0.01, 2.25))  # capped at 1, at least 0.01
    timing = harsh.only("timing")
    assert timing == Disturbances(timing=harsh.timing) and not timing.is_ideal
    assert timing.sensing.is_ideal and timing.acting.is_ideal and timing.communication.is_ideal


def test_a_randomised_profile_draws_each_episodes_level() -> None:
    """With ``randomise`` each team's episode meets the profile scaled by a level drawn from [0, 1], its gains within
    the scaled interval."""
    engine = make_engine(TASK, profile("harsh").randomised(), teams=4, seed=70)
    disturber = engine.disturber
    assert disturber is not None
    levels = disturber.levels.copy()
    assert np.all((levels >= 0) & (levels <= 1)) and len(set(levels.tolist())) == 4
    for team, level in enumerate(levels):
        episode = disturber.episodes[team]
        assert episode == profile("harsh").scaled(float(level)).randomised()
        low, high = 1 - 0.25 * level, 1 + 0.25 * level
        gains = disturber.gains[engine.team_rows(team)]
        assert np.all((gains >= low - 1e-12) & (gains <= high + 1e-12))


# 5. Validation ----------------------------------------------------------------------------------------------------------


def invalid_cases(folder: Path) -> list[tuple[Any, str]]:
    """(a call that must fail, a text the one-line message must hold)."""
    bad_file = folder / "bad.yaml"
    bad_file.write_text("sensing:\n  beam_dropout: 2.0\n")
    return [
        (lambda: Sensing(lidar_noise=-0.01), "sensing.lidar_noise=-0.01"),
        (lambda: Sensing(position_noise=math.nan), "sensing.position_noise"),
        (lambda: Sensing(drift_time=0.0), "sensing.drift_time"),
        (lambda: Communication(loss=1.5), "communication.loss=1.5"),
        (lambda: Sensing(beam_dropout=-0.1), "sensing.beam_dropout"),
        (lambda: Acting(gain=(1.1, 1.3)), "acting.gain"),
        (lambda: Acting(turn_gain=(0.0, 1.2)), "acting.turn_gain"),
        (lambda: Acting(gain=(0.9,)), "acting.gain"),  # type: ignore[arg-type]
        (lambda: Timing(observation_delay=(0, 1.5)), "timing.observation_delay"),  # type: ignore[arg-type]
        (lambda: Timing(action_delay=(2.0, 1.0)), "timing.action_delay"),
        (lambda: Timing(jitter=500.0), "timing.jitter"),
        (lambda: Communication(delay=(0.5, 1)), "communication.delay"),  # type: ignore[arg-type]
        (lambda: Disturbances.from_dict({"sensors": {}}), "unknown key(s) ['sensors']"),
        (lambda: Disturbances.from_dict({"sensing": {"lidar_nose": 0.1}}), "unknown sensing field(s) ['lidar_nose']"),
        (lambda: Disturbances.from_dict({"randomise": "yes"}), "randomise='yes'"),
        (lambda: Disturbances.from_dict({"profile": "stormy"}), "unknown disturbance profile 'stormy'"),
        (lambda: load_disturbances("stormy"), "'stormy' are neither a profile"),
        (lambda: load_disturbances(folder / "missing.yaml"), "missing.yaml"),
        (lambda: load_disturbances(bad_file), "sensing.beam_dropout=2.0"),
        (lambda: TASK.replace(disturbances="stormy"), "'stormy'"),
        (lambda: Disturbances().scaled(-1.0), "level"),
        (lambda: Disturbances().only("radio"), "'radio'"),
    ]


def test_bad_values_raise_one_line_value_errors_naming_the_field(tmp_path: Path) -> None:
    for call, text in invalid_cases(tmp_path):
        with pytest.raises(ValueError) as raised:
            call()
        message = str(raised.value)
        assert text in message and "\n" not in message, message
    with pytest.raises(ValueError) as raised:
        load_disturbances(tmp_path / "bad.yaml")
    message = str(raised.value)
    assert message.startswith(str(tmp_path / "bad.yaml")) and "[0, 1]" in message


# 6. Messages ------------------------------------------------------------------------------------------------------------


def sent_at(call: int, rows: int) -> np.ndarray:
    """The ``(rows, 1)`` messages sent at policy call ``call``: 100 (call + 1) + row, all distinct and nonzero."""
    return (100.0 * (call + 1) + np.arange(rows, dtype=np.float32))[:, None].astype(np.float32)


def started(communication: Communication, n_agents: int, n_teams: int, seed: int = 0) -> MessageChannel:
    channel = MessageChannel(communication, n_agents, n_teams)
    for team in range(n_teams):
        channel.start(team, seed + team)
    return channel


def ring_senders(n_agents: int, n_teams: int) -> np.ndarray:
    """Each row's preceding and succeeding neighbour's row, by hand."""
    return np.array(
        [
            [t * n_agents + (i - 1) % n_agents, t * n_agents + (i + 1) % n_agents]
            for t in range(n_teams)
            for i in range(n_agents)
        ]
    )


def test_message_delays_shift_each_senders_messages_by_whole_steps() -> None:
    """Without loss a receiver hears at call s what its neighbour j sent at call s - 1 - d_j (zeros before the
    episode's first message): first one delay of 1 for everyone, then delays drawn from [0, 2] per sender."""
    for delay in ((1, 1), (0, 2)):
        n_agents, n_teams = 3, 4
        rows = n_agents * n_teams
        channel = started(Communication(delay=delay), n_agents, n_teams)
        delays, senders = channel.delays.copy(), ring_senders(n_agents, n_teams)
        assert np.all((delays >= delay[0]) & (delays <= delay[1]))
        if delay == (0, 2):
            assert set(delays.tolist()) == {0, 1, 2}
        for call in range(8):
            received = channel.deliver(np.zeros((rows, 1), np.float32) if call == 0 else sent_at(call - 1, rows))
            for row in range(rows):
                for side, sender in enumerate(senders[row]):
                    origin = call - 1 - delays[sender]
                    expected = 0.0 if origin < 0 else sent_at(origin, rows)[sender, 0]
                    assert received[row, side, 0] == expected, (delay, call, row, side)


def test_a_lost_message_is_replaced_by_the_last_one_heard() -> None:
    """Loss 1: every receiver hears zeros forever. Loss 0.5: each message received is the one arriving or exactly
    the last one heard on that link; the share lost is 0.5 within its 99.9 % interval; the same seeds lose the same
    messages; a new episode of a team hears nothing until messages of that episode arrive."""
    n_agents, n_teams, calls = 5, 2, 1000
    rows = n_agents * n_teams
    deaf = started(Communication(loss=1.0), n_agents, n_teams)
    for call in range(20):
        assert not deaf.deliver(np.zeros((rows, 1), np.float32) if call == 0 else sent_at(call - 1, rows)).any()
    channel, twin = (started(Communication(loss=0.5), n_agents, n_teams, seed=9) for _ in range(2))
    senders, heard = ring_senders(n_agents, n_teams), np.zeros((rows, 2, 1), np.float32)
    lost = trials = 0
    for call in range(calls):
        sent = np.zeros((rows, 1), np.float32) if call == 0 else sent_at(call - 1, rows)
        received = channel.deliver(sent)
        assert np.array_equal(received, twin.deliver(sent))
        if call > 0:
            arriving = sent[senders]
            delivered = received == arriving
            assert np.all(delivered | (received == heard)), call
            lost, trials = lost + int((~delivered).sum()), trials + delivered.size
        heard = received
    assert_rate(lost, trials, 0.5, "message loss")
    channel.start(0, 99)  # team 0's next episode: nothing heard, then its own messages only
    first = channel.deliver(sent_at(calls - 1, rows))
    assert not first[:n_agents].any() and first[n_agents:].any()


class Relay(Policy):
    """A talking policy (M = 2): each row sends (its row + 1, its step count) and steers by what its preceding
    neighbour sent, scaled by 1/1000; it remembers what it heard."""

    def __init__(self, config: FormationConfig) -> None:
        self.config = config
        self.heard: list[np.ndarray | None] = []

    @property
    def message_size(self) -> int:
        return 2

    def _agent_step(
        self,
        observations: np.ndarray,
        agents: np.ndarray,
        state: Any,
        episode_start: np.ndarray | None,
        received: np.ndarray | None,
        deterministic: bool,
    ) -> AgentStep:
        rows = len(observations)
        steps = np.zeros(rows) if state is None else np.asarray(state) + 1.0
        self.heard.append(None if received is None else received.copy())
        actions = np.zeros((rows, 2), np.float32) if received is None else np.clip(received[:, :2] / 1000, -1, 1)
        messages = np.stack([np.arange(rows) + 1.0, steps], axis=1).astype(np.float32)
        return AgentStep(actions.astype(np.float32), steps, messages)

    def fit(self, config: FormationConfig) -> Policy:
        return self


def test_policy_predict_delivers_what_the_channel_says() -> None:
    """A talking policy's rows receive through ``predict(..., channel=)`` exactly what a twin channel (same links,
    same seeds) delivers of the messages the policy sent; its actions follow them; losses and delays make that differ
    from the lossless routing."""
    n_teams, communication = 2, Communication(loss=0.4, delay=(0, 1))
    rows_count = n_teams * TASK.n_agents
    observations = make_engine(TASK, teams=n_teams, seed=80).latest.observations.copy()
    policy = Relay(TASK)
    channel, twin = started(communication, TASK.n_agents, n_teams), started(communication, TASK.n_agents, n_teams)
    senders, state, differs = ring_senders(TASK.n_agents, n_teams), None, 0
    for call in range(30):
        sent = np.zeros((rows_count, 2), np.float32) if state is None else state[1]
        actions, state = policy.predict(observations, state, channel=channel)
        expected = twin.deliver(sent)
        heard = policy.heard[-1]
        assert heard is not None and np.array_equal(heard, expected.reshape(rows_count, 4)), call
        assert np.array_equal(actions, np.clip(expected[:, 0, :] / 1000, -1, 1).astype(np.float32))
        differs += int(call > 1 and not np.array_equal(expected, sent[senders]))
        assert np.array_equal(state[1][:, 1], np.full(rows_count, float(call)))
    assert differs > 10


# 7. Unicycles -----------------------------------------------------------------------------------------------------------


def test_the_harsh_profile_drives_unicycles_for_100_steps() -> None:
    """Harsh disturbances on unicycles: 100 steps of random actions give finite observations and agents inside the
    world (within Pymunk's allowed overlap of its border)."""
    config = TASK.replace(dynamics="unicycle", disturbances="harsh")
    engine = make_engine(config, teams=2, seed=90)
    disturber = engine.disturber
    assert disturber is not None and disturber.late and disturber.localises
    radius, slop = config.agent_radius, 0.02
    start = engine.latest.positions.copy()
    for action in np.random.default_rng(12).uniform(-1, 1, (100, 2 * config.n_agents, 2)):
        step = engine.step(action)
        assert np.isfinite(step.observations).all() and np.isfinite(step.positions).all()
        assert np.all(step.positions >= radius - slop)
        assert np.all(step.positions <= np.array([config.world_width, config.world_height]) - radius + slop)
        assert engine.live.all()
    assert np.abs(engine.latest.positions - start).max() > 0.05  # they drove
