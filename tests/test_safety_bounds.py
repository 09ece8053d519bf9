"""The safety filter under declared bounds (:class:`~sb3_formation.safety.filter.FilterBounds`, ``docs/disturbances.md``,
"A filter that stays safe under declared bounds"), against numbers computed by hand or by an independent route.

- **A wall ahead** with a declared lidar range error e: the fastest approach the filter allows is the discrete-time
  barrier's ``gamma (gap - margin - e) / (v_max dt)`` (units of v_max), ``gamma e / (v_max dt)`` less than without e.
- **A delayed action into a wall**: an agent that has sent full-speed actions towards a wall brakes its delay's travel
  earlier, and eq. 19 by hand (``v <- clamp(v + a F_max dt / m, v_max)``, ``x <- x + v dt``) over the delay and the
  step under the filtered action keeps the barrier, for every delay of a window (a seeded search).
- **A weak actuator**: a declared gain interval [0.75, 1.25] moves the wall closer by the error of the largest action,
  ``0.25 sqrt(2) F_max dt^2 / m``; in the engine, with an actual gain of 0.75 or 1.25, the agent keeps the margin.
- **A jittered delay**: an action may hold half a step longer or shorter; each step of the window then adds the
  change between two actions acting that long, piled up and capped at 2 v_max (the true and the predicted velocity
  both lie within v_max); in the engine the agent keeps the margin.
- **Two neighbours' estimates**: their position errors are independent, so their offset's bound is sqrt(2) times one's
  deviation times 3.41, not twice one's bound.
- **The property**: random scenes, errors within the declared bounds, adversarial actions: no contact except on the
  agent-steps the filter reported infeasible (or within the delay they span).
- **The ideal filter is unchanged**: ideal disturbances declare no bound, and such a filter is the exact one, bit for bit.

The thesis's sizes give simple numbers: v_max dt = 0.015 m (a step's travel), F_max dt / m = 0.05 m/s = v_max (a full
action changes the velocity by v_max), R_a = 0.2 m, 90 lidar rays 4 deg apart, gamma = 0.5, margins 0.01 m.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from sb3_formation.controllers.base import AgentStep, Policy
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.disturbances import Acting, Disturbances, Sensing, Timing, profile
from sb3_formation.env.engine import ContactColumn, FormationEngine
from sb3_formation.env.observations import observation_fields, observation_layout
from sb3_formation.env.scenarios import Scenario
from sb3_formation.env.sensors import ray_directions
from sb3_formation.safety.filter import FilterBounds, SafetyFilter, SafetyGains, SentCommands
from sb3_formation.safety.policy import SafePolicy

CONFIG = FormationConfig.task("ch5-bearing", stage=3)
SMALL = FormationConfig.task("ch4-individual", stage=3)  # three agents, for hand-placed runs in the engine
LAYOUT = observation_layout(observation_fields(CONFIG))
ROW_SIZE = sum(field.size for field in observation_fields(CONFIG))
GAINS = SafetyGains()
GAMMA, MARGIN, RHO = GAINS.gamma, GAINS.obstacle_margin, GAINS.slack_weight
V_MAX, DT, RADIUS = CONFIG.v_max, CONFIG.dt, CONFIG.agent_radius
STEP = V_MAX * DT  # m: a step's travel at v_max, the unit of the barriers' right-hand sides
PUSH = CONFIG.force_max * DT / CONFIG.agent_mass  # m/s: the velocity change of a full action (eq. 19)
DIRECTIONS = ray_directions(CONFIG.lidar_rays)


def test_hand_constants() -> None:
    """The numbers the hand computations below rely on."""
    assert STEP == pytest.approx(0.015, rel=1e-12) and PUSH == pytest.approx(V_MAX, rel=1e-12)
    assert (RADIUS, CONFIG.lidar_rays, CONFIG.lidar_range, GAMMA, MARGIN, RHO) == (0.2, 90, 1.5, 0.5, 0.01, 1e4)
    assert (SMALL.lidar_rays, SMALL.lidar_range, SMALL.agent_radius) == (90, 1.5, 0.2)
    assert np.allclose(DIRECTIONS[0], [1.0, 0.0])  # ray 0 looks along +x


# Hand-built rows ------------------------------------------------------------------------------------------------------


def wall_readings(gap: float, rays: int = CONFIG.lidar_rays, lidar_range: float = CONFIG.lidar_range) -> np.ndarray:
    """The obstacle channel of an agent whose surface is ``gap`` (m) from a straight wall across +x (the world's
    border): the ray at angle theta (|theta| < 90 deg) meets it ``(R_a + gap) / cos(theta)`` from the agent's centre,
    and reads that less R_a, as a share of the range (1: nothing within range)."""
    cosines = ray_directions(rays)[:, 0]
    readings = np.ones(rays)
    ahead = cosines > 1e-9
    readings[ahead] = np.minimum(((RADIUS + gap) / cosines[ahead] - RADIUS) / lidar_range, 1.0)
    return readings


def wall_row(gap: float, velocity: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """A raw row of :data:`CONFIG`: a wall ``gap`` (m) ahead along +x, the agent's velocity (m/s), nothing else in
    lidar range, its ring neighbours 1.13 m away (no neighbour barrier can bind within a step)."""
    row = np.zeros(ROW_SIZE)
    row[LAYOUT["lidar_obstacles"]] = wall_readings(gap)
    row[LAYOUT["lidar_agents"]] = 1.0
    row[LAYOUT["neighbour_offsets"]] = [-0.8, 0.8, -0.8, -0.8]
    row[LAYOUT["velocity"]] = velocity
    return row


def projected(target: float, bound: float) -> float:
    """The solution u of ``min (u - target)^2 + rho s^2`` with ``u - s <= bound`` (bound < target), by hand (as in
    ``tests/test_safety.py``): s = (target - bound) / (1 + rho)."""
    return bound + (target - bound) / (1.0 + RHO)


def bound_of(solution: float, target: float) -> float:
    """The bound that :func:`projected` turns ``target`` into ``solution``: its inverse."""
    return (solution * (1.0 + RHO) - target) / RHO


def clamp(velocity: np.ndarray) -> np.ndarray:
    """Eq. 19's speed clamp by hand: a velocity (m/s) faster than v_max scaled down to v_max."""
    speed = float(np.hypot(*velocity))
    return velocity * (V_MAX / speed) if speed > V_MAX else velocity


def eq19(velocity: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 19 by hand from rest at the origin with ``velocity`` (m/s), each action held for a step:
    ``v <- clamp(v + a F_max dt / m)``, ``x <- x + v dt``; the position (m) and the velocity at the end."""
    position = np.zeros(2)
    for action in actions:
        velocity = clamp(velocity + np.asarray(action, dtype=np.float64) * PUSH)
        position = position + velocity * DT
    return position, velocity


def allowed_speed(safety: SafetyFilter, row: np.ndarray, sent: np.ndarray | None = None) -> float:
    """The fastest approach towards +x (units of v_max) the filter lets a row command, read off two ways that must
    agree: from the solution of a full-speed proposal (the hand-solved QP inverted), and as the edge between a
    commanded speed 1e-7 below it, which comes back bit for bit, and one 1e-7 above it, which is changed."""
    full = np.array([[1.0, 0.0]])
    safe, report = safety.filter(row[None], full, None if sent is None else sent[None])
    velocity = row[LAYOUT["velocity"]][0] / V_MAX
    if sent is not None:
        velocity = eq19(row[LAYOUT["velocity"]], sent)[1][0] / V_MAX
    target = min(velocity + 1.0, 1.0)
    assert report.changed[0] and not report.infeasible[0]
    speed = bound_of(velocity + float(safe[0, 0]), target)
    for offset, changed in ((-1e-7, False), (1e-7, True)):
        proposal = np.array([[speed + offset - velocity, 0.0]])
        again, again_report = safety.filter(row[None], proposal, None if sent is None else sent[None])
        assert bool(again_report.changed[0]) is changed
        assert np.array_equal(again, proposal) is not changed
    return speed


# 1. A wall ahead with a declared lidar bound ----------------------------------------------------------------------------


def test_the_hand_built_wall_reads_as_the_engines_lidar() -> None:
    """An agent placed ``gap`` from the world's right border in the engine reads what :func:`wall_readings` says
    (float32 rounding aside): the hand-built rows below are rows the engine writes."""
    gap = 0.03
    engine = FormationEngine([SMALL])
    positions = np.array([[SMALL.world_width - RADIUS - gap, 5.0], [7.0, 3.0], [7.0, 7.0]])
    rows = engine.reset(0, seed=0, scenario=Scenario(positions, np.array([3.0, 5.0])))
    layout = observation_layout(observation_fields(SMALL))
    read = rows[0, layout["lidar_obstacles"]].astype(np.float64)
    np.testing.assert_allclose(read, wall_readings(gap, SMALL.lidar_rays, SMALL.lidar_range), rtol=1e-6, atol=1e-7)
    assert read[0] == pytest.approx(gap / SMALL.lidar_range, rel=1e-6)
    assert (read < 1).sum() == 41  # the rays within 80 deg of +x: (R_a + gap) / cos(theta) - R_a < 1.5 m


def test_a_declared_range_error_moves_the_wall_closer_by_it() -> None:
    """Gap 3 cm, lidar noise 2 mm declared at 3 standard deviations: e = 6 mm. The fastest approach the filter allows
    is ``gamma (gap - margin - e) / (v_max dt)`` = 0.5 * 14 mm / 15 mm = 0.4667 v_max (it was 0.6667 without e),
    ``gamma e / (v_max dt)`` = 0.2 v_max less; a full-speed proposal from rest comes back as the hand-solved QP's
    solution."""
    gap, noise = 0.03, 0.002
    declared = FilterBounds.declared(Disturbances(sensing=Sensing(lidar_noise=noise)))
    error = declared.range_error
    assert error == pytest.approx(3 * noise, rel=1e-12)
    assert declared == FilterBounds(range_error=error)  # nothing else declared
    row = wall_row(gap)
    robust, exact = SafetyFilter(CONFIG, bounds=declared), SafetyFilter(CONFIG, bounds=FilterBounds())
    with_error, without = allowed_speed(robust, row), allowed_speed(exact, row)
    assert with_error == pytest.approx(GAMMA * (gap - MARGIN - error) / STEP, abs=1e-9)
    assert with_error == pytest.approx(0.4667, abs=1e-4) and without == pytest.approx(2 / 3, abs=1e-9)
    assert without - with_error == pytest.approx(GAMMA * error / STEP, abs=1e-9)
    assert without - with_error == pytest.approx(0.2, abs=1e-9)
    safe, report = robust.filter(row[None], np.array([[1.0, 0.0]]))
    np.testing.assert_allclose(safe[0], [projected(1.0, GAMMA * (gap - MARGIN - error) / STEP), 0.0], rtol=0, atol=1e-9)
    assert report.separation[0] == pytest.approx(gap)


# 2. A delayed action into a wall ----------------------------------------------------------------------------------------

#: one step of observation delay and one of action delay: the action chosen now arrives two steps after its row
DELAYED = Disturbances(timing=Timing(observation_delay=(1, 1), action_delay=(1.0, 1.0)))
#: the agent moves at v_max / 2 towards the wall in its row and has sent two full-speed actions towards it since
SENSED_VELOCITY = (0.5 * V_MAX, 0.0)
SENT = np.array([[1.0, 0.0], [1.0, 0.0]])


def test_a_delayed_agent_brakes_its_delays_travel_earlier() -> None:
    """By hand: from v_max / 2, the two actions sent reach v_max (clamped) after one step, so the new action arrives
    2 v_max dt = 3 cm nearer the wall than the row shows, at v_max. A full-speed action then commands v_max, which the
    barrier allows while ``gamma (gap - travel - margin) / (v_max dt) >= 1``: the exact filter changes it below a gap
    of margin + v_max dt / gamma = 4 cm, the delayed one below 4 + 3 = 7 cm. Its largest allowed speed at a gap of
    5 cm is 0.5 * (50 - 30 - 10) / 15 = 1/3 v_max."""
    bounds = FilterBounds.declared(DELAYED)
    assert bounds.delay == (2.0, 2.0) and bounds.horizon == 2
    position, velocity = eq19(np.array(SENSED_VELOCITY), SENT)
    assert position == pytest.approx([2 * STEP, 0.0], abs=1e-15) and velocity == pytest.approx([V_MAX, 0.0], abs=1e-15)
    delayed, exact = SafetyFilter(CONFIG, bounds=bounds), SafetyFilter(CONFIG, bounds=FilterBounds())
    sent = SentCommands(bounds.horizon)
    sent.rows(1, None)
    for action in SENT:
        sent.add(action[None])
    assert np.array_equal(sent.rows(1, None)[0], SENT)  # newest last
    full = np.array([[1.0, 0.0]])
    earlier = MARGIN + STEP / GAMMA + 2 * STEP
    for gap, exact_brakes, delayed_brakes in [(0.035, True, True), (0.05, False, True), (0.065, False, True)]:
        row = wall_row(gap, SENSED_VELOCITY)
        assert exact.filter(row[None], full)[1].changed[0] == exact_brakes, gap
        assert delayed.filter(row[None], full, sent.rows(1, None))[1].changed[0] == delayed_brakes, gap
    for gap, brakes in [(earlier - 1e-6, True), (earlier + 1e-6, False)]:  # the edge: 7 cm
        assert delayed.filter(wall_row(gap, SENSED_VELOCITY)[None], full, sent.rows(1, None))[1].changed[0] == brakes
    assert not exact.filter(wall_row(MARGIN + STEP / GAMMA + 1e-6, SENSED_VELOCITY)[None], full)[1].changed[0]
    assert allowed_speed(delayed, wall_row(0.05, SENSED_VELOCITY), SENT) == pytest.approx(1 / 3, abs=1e-9)


def test_the_predicted_position_under_the_filtered_action_keeps_the_barrier() -> None:
    """Gap 5 cm, the delay's two full-speed actions sent: by hand (eq. 19) the agent arrives at 3 cm, 1 cm from the
    margin (h = 10 mm), and the filtered action's step ends at h = (1 - gamma) 10 mm = 5 mm (less the QP's slack,
    (1 - 1/3) / (1 + rho) v_max dt = 1 um). The exact filter lets the full-speed action through: its step ends 5 mm
    inside the margin."""
    gap = 0.05
    row = wall_row(gap, SENSED_VELOCITY)
    full = np.array([[1.0, 0.0]])
    delayed = SafetyFilter(CONFIG, bounds=FilterBounds.declared(DELAYED))
    safe, report = delayed.filter(row[None], full, SENT[None])
    assert report.changed[0] and not report.infeasible[0]
    assert safe[0] == pytest.approx([projected(1.0, 1 / 3) - 1.0, 0.0], abs=1e-9)  # it brakes: -2/3 of F_max
    arrived, _ = eq19(np.array(SENSED_VELOCITY), SENT)
    ended, _ = eq19(np.array(SENSED_VELOCITY), np.concatenate([SENT, safe]))
    before, after = gap - arrived[0] - MARGIN, gap - ended[0] - MARGIN
    assert before == pytest.approx(0.010, abs=1e-12)
    slack = (1.0 - 1 / 3) / (1.0 + RHO) * STEP
    assert after == pytest.approx((1 - GAMMA) * before - slack, abs=1e-9)
    assert after == pytest.approx(0.005, abs=2e-6)
    unfiltered, _ = SafetyFilter(CONFIG, bounds=FilterBounds()).filter(row[None], full)
    ended, _ = eq19(np.array(SENSED_VELOCITY), np.concatenate([SENT, unfiltered]))
    assert gap - ended[0] - MARGIN == pytest.approx(-0.005, abs=1e-12)


@pytest.mark.parametrize("longest", [1, 2, 3])
def test_every_delay_of_a_window_keeps_its_barrier(longest: int) -> None:
    """A window of delays 0 to ``longest`` steps: 400 seeded rows of a wall 0 to 12 cm ahead, a random sensed
    velocity, random actions sent, a full-speed proposal towards the wall. For each delay d of the window, eq. 19 by
    hand moves the agent under its last d actions, then a step under the filtered action; where the filter reported
    the step feasible and every arrival lies outside the margin, the step keeps the barrier of the wall's true distance,
    ``h_end >= (1 - gamma) h_arrival``, to 0.4 mm: the point of the wall straight ahead of a shifted agent lies between
    two rays 4 deg apart, up to 0.3 mm nearer than either ray's return at these distances.

    (Before the fixes in ``filter.py`` a filter kept this for the longest delay only, breaking it by up to 12 mm for
    the others: each later delay read the wall from the gap found for the first, the barriers were written for a point
    shifted by the velocity difference instead of for the arrival, and a clamped command moved otherwise at a shorter
    delay.)"""
    safety = SafetyFilter(CONFIG, bounds=FilterBounds(delay=(0.0, float(longest))))
    rng = np.random.default_rng(longest)
    checked, worst = 0, -np.inf
    for trial in range(400):
        gap = rng.uniform(0.0, 0.12)
        velocity = clamp(rng.uniform(-1.0, 1.0, 2) * V_MAX)
        sent = rng.choice([-1.0, 0.0, 1.0], size=(longest, 2)) if trial % 2 else rng.uniform(-1.0, 1.0, (longest, 2))
        proposal = np.array([[1.0, rng.uniform(-1.0, 1.0)]])
        safe, report = safety.filter(wall_row(gap, tuple(velocity))[None], proposal, sent[None])
        if report.infeasible[0]:
            continue
        steps = [(gap - eq19(velocity, sent[longest - d :])[0][0] - MARGIN) for d in range(longest + 1)]
        if min(steps) < 0:
            continue
        for d, arrival in zip(range(longest + 1), steps):
            end = gap - eq19(velocity, np.concatenate([sent[longest - d :], safe]))[0][0] - MARGIN
            worst = max(worst, (1 - GAMMA) * arrival - end)
        checked += 1
    assert checked > 150
    assert worst < 0.0004


def pushed_into_the_border(
    disturbances: Disturbances, bounds: FilterBounds, action: tuple[float, float], gain: float | None = None, steps: int = 80
) -> tuple[np.ndarray, int, int]:
    """Agent 0 of a team of three starts at rest 0.3 m from the world's right border and proposes ``action`` at every
    step behind a :class:`SafetyFilter` of ``bounds`` (with :class:`SentCommands`), in an engine with
    ``disturbances`` (and every motor gain set to ``gain`` after the reset's draw); its ring neighbours, 1.4 m behind
    it, propose nothing. Its true gap (m) to the border after each step, and its obstacle contacts and the steps the
    filter reported infeasible for it over the run."""
    start = SMALL.world_width - RADIUS - 0.3
    positions = np.array([[start, 5.0], [start - 1.0, 6.0], [start - 1.0, 4.0]])
    config = SMALL.replace(disturbances=disturbances)
    engine = FormationEngine([config])
    rows = engine.reset(0, seed=0, scenario=Scenario(positions, np.array([3.0, 5.0])))
    if gain is not None:
        assert engine.disturber is not None
        engine.disturber.gains[:] = gain
    safety, sent = SafetyFilter(config, bounds=bounds), SentCommands(bounds.horizon)
    proposed = np.zeros((3, 2))
    proposed[0] = action
    gaps, contacts, reported = [], 0, 0
    for _ in range(steps):
        safe, report = safety.filter(rows, proposed, sent.rows(3, None))
        sent.add(safe)
        step = engine.step(safe)
        rows = step.observations
        gaps.append(SMALL.world_width - RADIUS - step.positions[0, 0])
        contacts += int(step.contacts[0, ContactColumn.OBSTACLES])
        reported += int(report.infeasible[0])
    return np.array(gaps), contacts, reported


@pytest.mark.parametrize("action", [(1.0, 0.0), (1.0, 1.0), (1.0, -0.4)])
def test_a_delayed_approach_in_the_engine_keeps_the_margin(action: tuple[float, float]) -> None:
    """Two steps of delay in the engine (one of observation, one of action): behind the filter that declares them the
    agent pushing into the border never comes nearer than the margin (1 cm, to 0.01 mm; measured 9.997, 11.41 and
    10.73 mm by the three proposals), ends within 2 mm of it and is never reported infeasible; behind the exact filter
    it runs into the wall (measured: 0.01 to 6.1 mm past the wall's surface, 6 to 8 contacts)."""
    gaps, contacts, reported = pushed_into_the_border(DELAYED, FilterBounds.declared(DELAYED), action)
    assert contacts == 0 and reported == 0 and gaps.min() >= MARGIN - 1e-5
    assert gaps[-1] < MARGIN + 0.002  # it came to the margin, not short of it
    gaps, contacts, _ = pushed_into_the_border(DELAYED, FilterBounds(), action)
    assert gaps.min() < 0 and contacts > 0


# 3. A weak actuator -----------------------------------------------------------------------------------------------------

#: motors whose gains may lie anywhere in [0.75, 1.25]
WORN = Disturbances(acting=Acting(gain=(0.75, 1.25)))
#: by hand: the largest move error over a step, the gain error of the largest action (a corner of the box, |a| =
#: sqrt(2)) held for a step: 0.25 * sqrt(2) * 0.05 m/s * 0.3 s = 5.303 mm
GAIN_ERROR = 0.25 * math.sqrt(2.0) * PUSH * DT


def test_a_declared_gain_interval_moves_the_wall_closer_by_the_largest_actions_error() -> None:
    """Gap 3 cm: the fastest approach falls from 0.6667 v_max to 0.5 * (30 - 10 - 5.303) mm / 15 mm = 0.4899 v_max,
    by gamma * 5.303 mm / 15 mm = 0.1768 v_max."""
    bounds = FilterBounds.declared(WORN)
    assert bounds == FilterBounds(gain=(0.75, 1.25))
    assert GAIN_ERROR == pytest.approx(0.0053033, abs=1e-7)
    gap = 0.03
    worn = allowed_speed(SafetyFilter(CONFIG, bounds=bounds), wall_row(gap))
    exact = allowed_speed(SafetyFilter(CONFIG, bounds=FilterBounds()), wall_row(gap))
    assert worn == pytest.approx(GAMMA * (gap - MARGIN - GAIN_ERROR) / STEP, abs=1e-9)
    assert worn == pytest.approx(0.4899, abs=1e-4)
    assert exact - worn == pytest.approx(0.25 * math.sqrt(2.0) * GAMMA, abs=1e-9)  # 0.1768


@pytest.mark.parametrize("gain", [0.75, 1.25])
@pytest.mark.parametrize("action", [(1.0, 0.0), (1.0, 1.0), (1.0, -0.4)])
def test_a_weak_or_strong_actuator_keeps_the_margin_behind_the_filter(gain: float, action: tuple[float, float]) -> None:
    """In the engine with every motor gain at 0.75 or 1.25 (the interval's ends; set after the reset, since a gain
    interval must hold 1), the agent pushing into the border behind the filter that declares [0.75, 1.25] touches
    nothing and keeps the margin (measured: 14.7 mm at the nearest); pushing straight at it, it comes to rest at the
    grown margin, 10 + 5.303 mm (to 0.01 mm). Behind the exact filter a gain of 0.75 brakes too weakly and comes inside
    the margin (measured: 9.44 mm straight on)."""
    gaps, contacts, reported = pushed_into_the_border(WORN, FilterBounds.declared(WORN), action, gain)
    assert contacts == 0 and reported == 0 and gaps.min() >= MARGIN
    if action == (1.0, 0.0):
        assert gaps[-1] == pytest.approx(MARGIN + GAIN_ERROR, abs=1e-5)
    if gain == 0.75 and action == (1.0, 0.0):
        exact_gaps, _, _ = pushed_into_the_border(WORN, FilterBounds(), action, gain)
        assert exact_gaps.min() < MARGIN - 0.0005


# 4. The property: no contact but on steps reported infeasible ------------------------------------------------------------

SCENES = ("curriculum", "passage", "corridor", "trap", "clutter")
KINDS = ("random", "nearest", "obstacle")
#: the Gaussian errors' bound: TAIL times the declared bound of 3 standard deviations (3.41 for a 2-D error), so 6
#: (6.82) standard deviations; a draw beyond it has a probability of 2e-9 (8e-11), against about 10^7 draws in all
TAIL = 2.0
#: steps per case
STEPS = 150
#: how much nearer than the margin a surface may come between two lidar rays 4 deg apart (``docs/safety.md``)
LIDAR_SPACING_ERROR = 0.0004


def case_disturbances(rng: np.random.Generator) -> Disturbances:
    """One case's disturbances: every part at a random level, Gaussian errors small enough that their 6-sigma bounds
    leave room to move (a lidar's 2 mm, a localisation's 2 + 2 mm and 0.3 deg, 1 % of v_max), gains within [0.75,
    1.25], force noise up to 2 % of F_max, delays up to 2 + 2 steps with up to half a step of jitter."""

    def some(value: float) -> float:
        return float(value * rng.choice([0.0, rng.uniform(0.3, 1.0)]))

    return Disturbances(
        sensing=Sensing(
            lidar_noise=some(0.002),
            beam_dropout=some(0.05),
            position_noise=some(0.002),
            position_drift=some(0.002),
            heading_noise_deg=some(0.3),
            heading_drift_deg=some(0.3),
            velocity_noise=some(0.0005),
        ),
        acting=Acting(gain=(1.0 - some(0.25), 1.0 + some(0.25)), force_noise=some(0.02)),
        timing=Timing(
            observation_delay=(0, int(rng.integers(0, 3))),
            action_delay=(0.0, some(2.0)),
            jitter=float(rng.choice([0.0, 0.25, 0.5])),
        ),
    )


def adversarial_actions(rows: np.ndarray, config: FormationConfig, rng: np.random.Generator, kind: str) -> np.ndarray:
    """Every agent acts at random, drives at the nearest thing it reads (a lidar return of either channel or a ring
    neighbour), or at the nearest obstacle return; a little noise on top."""
    if kind == "random":
        return rng.uniform(-1, 1, (len(rows), 2))
    layout = observation_layout(observation_fields(config))
    directions = ray_directions(config.lidar_rays)
    actions = np.empty((len(rows), 2))
    for agent, row in enumerate(rows):
        obstacles = row[layout["lidar_obstacles"]] * config.lidar_range
        readings = obstacles if kind == "obstacle" else np.minimum(obstacles, row[layout["lidar_agents"]] * config.lidar_range)
        offsets = row[layout["neighbour_offsets"]].reshape(2, 2)
        gaps = np.linalg.norm(offsets, axis=1) - 2 * config.agent_radius
        if kind == "obstacle" or readings.min() < gaps.min():
            direction = directions[int(readings.argmin())]
        else:
            direction = offsets[int(gaps.argmin())] / np.linalg.norm(offsets[int(gaps.argmin())])
        actions[agent] = direction + rng.normal(0, 0.2, 2)
    return np.clip(actions, -1, 1)


def realised_errors(engine: FormationEngine, positions: np.ndarray, velocities: np.ndarray) -> dict[str, float]:
    """The largest errors the engine's agents sensed at the last step, against the truth: a beam's range error (m,
    beams not dropped), the distance of a position estimate, a heading error (rad), and a velocity estimate's white
    error (m/s: the estimate minus the true velocity turned by the heading error)."""
    sensed, config = engine.sensed, engine.config
    if sensed is None:
        return {}
    errors: dict[str, float] = {"position": float(np.hypot(*(sensed.positions - positions).T).max())}
    if sensed.beam_noise.size:
        errors["range"] = float(np.abs(np.where(sensed.dropped, 0.0, sensed.beam_noise)).max() * config.lidar_range)
    if sensed.heading_errors.size:
        turn = sensed.heading_errors
        cos, sin = np.cos(turn), np.sin(turn)
        turned = np.stack(
            [cos * velocities[:, 0] - sin * velocities[:, 1], sin * velocities[:, 0] + cos * velocities[:, 1]], 1
        )
        errors["heading"] = float(np.abs(turn).max())
        errors["velocity"] = float(np.hypot(*(sensed.velocities - turned).T).max())
    return errors


def obstacle_clearance(positions: np.ndarray, scenario: Scenario, config: FormationConfig) -> np.ndarray:
    """Each agent's true gap (m) to the nearest obstacle, by hand geometry: the world's border, the circles
    (``|p - c| - r - R_a``) and the walls (capsules: the distance to the segment less half the thickness, less R_a)."""
    x, y = positions[:, 0], positions[:, 1]
    gaps = [np.minimum.reduce([x, config.world_width - x, y, config.world_height - y]) - config.agent_radius]
    for cx, cy, radius in scenario.obstacles:
        gaps.append(np.hypot(x - cx, y - cy) - radius - config.agent_radius)
    for x0, y0, x1, y1, thickness in scenario.walls:
        start, along = np.array([x0, y0]), np.array([x1 - x0, y1 - y0])
        share = np.clip((positions - start) @ along / max(float(along @ along), 1e-300), 0.0, 1.0)
        nearest = start + share[:, None] * along
        gaps.append(np.hypot(*(positions - nearest).T) - 0.5 * thickness - config.agent_radius)
    clearance: np.ndarray = np.min(gaps, axis=0)
    return clearance


def run_case(case: int) -> dict[str, Any]:
    """One case of the property: its scene, team, disturbances and kind of actions drawn from seed ``case``, every agent
    behind a :class:`SafetyFilter` of the declared bounds (``FilterBounds.declared(d, tail=TAIL)``) with
    :class:`SentCommands`, for :data:`STEPS` steps. Returns the per-step infeasible reports, contacts and true gaps to
    the obstacles, the bounds, and the largest realised sensing errors."""
    rng = np.random.default_rng(case)
    disturbances = case_disturbances(rng)
    config = CONFIG.replace(
        scenes=SCENES[case % len(SCENES)], n_agents=int(rng.integers(3, 9)), max_steps=STEPS, disturbances=disturbances
    )
    kind = KINDS[case % len(KINDS)]
    bounds = FilterBounds.declared(disturbances, tail=TAIL)
    engine = FormationEngine([config])
    rows = engine.reset(0, seed=case)
    safety, sent = SafetyFilter(config, bounds=bounds), SentCommands(bounds.horizon)
    infeasible, contacts, clearances = [], [], []
    realised = dict.fromkeys(("range", "position", "heading", "velocity"), 0.0)
    for _ in range(STEPS):
        safe, report = safety.filter(rows, adversarial_actions(rows, config, rng, kind), sent.rows(len(rows), None))
        sent.add(safe)
        step = engine.step(safe)
        rows = step.observations
        infeasible.append(report.infeasible.copy())
        contacts.append(step.contacts.copy())
        clearances.append(obstacle_clearance(step.positions, engine.scenarios[0], config))
        for name, value in realised_errors(engine, step.positions, step.velocities).items():
            realised[name] = max(realised[name], value)
        if step.terminated[0] or step.truncated[0]:
            break
    return {
        "infeasible": np.array(infeasible),
        "contacts": np.array(contacts),
        "clearances": np.array(clearances),
        "bounds": bounds,
        "realised": realised,
        "config": config,
        "kind": kind,
    }


def unexcused_contacts(infeasible: np.ndarray, contacts: np.ndarray, horizon: int) -> list[tuple[int, int, str]]:
    """The agent-steps (step, agent, what) with a contact that no infeasible report excuses: an agent's contact at step
    k is excused by an infeasible report of its own at any step from k - horizon - 1 to k (the motion of step k comes
    from actions chosen up to ``horizon`` whole steps before, and a part-step delay lets one chosen a step earlier still
    hold at its start), and an agent contact also by such a report of any agent of the team touching an agent at
    step k (the barrier between two agents is shared: each keeps half, and one that did not may take more)."""
    found = []
    for step, agent in zip(*np.nonzero(contacts.sum(axis=2))):
        window = slice(max(0, step - horizon - 1), step + 1)
        agents = [agent]
        if contacts[step, agent, ContactColumn.AGENTS]:
            agents += list(np.flatnonzero(contacts[step, :, ContactColumn.AGENTS]))
        if not infeasible[window][:, agents].any():
            found.append((int(step), int(agent), "agent" if contacts[step, agent, ContactColumn.AGENTS] else "obstacle"))
    return found


@pytest.mark.parametrize("case", range(24))
def test_no_contact_but_on_steps_reported_infeasible(case: int) -> None:
    """Random scenes (stage 3 and every family, cycling), teams of 3 to 8, disturbances of every part drawn at random
    levels (:func:`case_disturbances`: sensing noise and dropped beams, gains and force noise, observation and action
    delays with jitter), adversarial actions (random, at the nearest thing, at the nearest obstacle), every agent
    behind a filter of the declared bounds: no contact on an agent-step that the filter did not report infeasible in
    that step or the steps its delay spans (:func:`unexcused_contacts`).

    The errors stay within the declared bounds: the Gaussian ones are declared at ``tail = 2`` (6 standard deviations,
    6.82 for the 2-D ones), where a draw beyond is practically impossible, and the sensing errors each step realised are
    measured against the truth (``engine.sensed``) and checked within their bounds; gains, delays and jitter are
    bounded by their intervals. (Force noise is not exposed by the engine: its bound rests on the tail alone.)

    The barrier itself holds: until an agent's first infeasible report its true gap to every obstacle
    (:func:`obstacle_clearance`) stays at the 1 cm margin or beyond, to the 0.4 mm the lidar's ray spacing allows.
    (Measured over the 24 cases: no contact at all, 196 infeasible agent-steps of 19,950; agents driven at the
    obstacles come within a few mm of their grown margins, e.g. 10.2 mm where the declared bounds make it 10.6 mm.)"""
    result = run_case(case)
    bounds, realised = result["bounds"], result["realised"]
    assert realised["range"] <= bounds.range_error and realised["position"] <= bounds.position_error
    assert realised["heading"] <= bounds.heading_error and realised["velocity"] <= bounds.velocity_error
    unexcused = unexcused_contacts(result["infeasible"], result["contacts"], bounds.horizon)
    config = result["config"]
    assert not unexcused, (
        f"case {case}: {config.scenes}, n={config.n_agents}, {result['kind']} actions, {bounds}: contacts on steps the "
        f"filter did not report infeasible (step, agent, what): {unexcused}"
    )
    infeasible, clearances = result["infeasible"], result["clearances"]
    first = np.where(infeasible.any(axis=0), infeasible.argmax(axis=0), len(infeasible))
    for agent in range(config.n_agents):
        kept = clearances[: first[agent], agent]
        assert not len(kept) or kept.min() >= MARGIN - LIDAR_SPACING_ERROR, (case, agent, kept.min())


def allowed_at_rest(bounds: FilterBounds, gap: float) -> float:
    """:func:`allowed_speed` of an agent at rest ``gap`` (m) from the wall ahead that has sent nothing over its window
    (zero actions), behind a filter of ``bounds``."""
    return allowed_speed(SafetyFilter(CONFIG, bounds=bounds), wall_row(gap), np.zeros((bounds.horizon, 2)))


#: one step of action delay with half a step of jitter (harsh's jitter): the window (1, 1.5), whole delays 1 and 2
JITTERED = Disturbances(timing=Timing(action_delay=(1.0, 1.0), jitter=0.5))
#: the velocity error (m/s) each step of a window piles up from jitter: two actions at most 2 sqrt 2 apart, one acting
#: half a step longer than the other
JITTER_ERROR = 0.5 * 2.0 * math.sqrt(2.0) * PUSH


def test_a_jittered_delay_moves_the_wall_closer_by_the_capped_errors_of_its_window() -> None:
    """Horizon 2, so three steps (two of delay, the action's own) each add the jitter's velocity error, piled up and
    capped at 2 v_max: (min(0.0707, 0.1) + min(0.1414, 0.1) + min(0.2121, 0.1)) m/s * 0.3 s = 81.2 mm (uncapped
    127.3 mm). An agent at rest with nothing sent, 10 cm from a wall, may approach at most
    0.5 * (100 - 10 - 81.2) mm / 15 mm = 0.2929 v_max."""
    bounds = FilterBounds.declared(JITTERED)
    assert bounds == FilterBounds(delay=(1.0, 1.5), jitter=0.5) and bounds.horizon == 2
    assert JITTER_ERROR == pytest.approx(0.070711, abs=1e-6)
    error = sum(min(k * JITTER_ERROR, 2 * V_MAX) for k in (1, 2, 3)) * DT
    assert error == pytest.approx(0.081213, abs=1e-6)
    gap = 0.1
    allowed = allowed_at_rest(bounds, gap)
    assert allowed == pytest.approx(GAMMA * (gap - MARGIN - error) / STEP, abs=1e-9)
    assert allowed == pytest.approx(0.2929, abs=1e-4)


def test_a_jittered_delay_in_the_engine_keeps_the_margin() -> None:
    """One step of action delay with half a step of jitter, the agent 0.3 m from the border pushing into it along
    (1, 0.5) at every step (engine seeded 0): no step reported infeasible, no contact, and the margin kept (measured:
    91.9 mm at the nearest; before jitter entered the margins this run came to 5.14 mm, inside the 10 mm margin).
    Straight at it, the same: no contact, the margin kept (80.3 mm), 4 steps reported infeasible."""
    bounds = FilterBounds.declared(JITTERED)
    gaps, contacts, reported = pushed_into_the_border(JITTERED, bounds, (1.0, 0.5))
    assert contacts == 0 and reported == 0 and gaps.min() >= MARGIN
    gaps, contacts, reported = pushed_into_the_border(JITTERED, bounds, (1.0, 0.0))
    assert contacts == 0 and gaps.min() >= MARGIN


def test_force_noise_over_a_delay_adds_as_independent_draws() -> None:
    """Force noise of 2 % of F_max with two steps of action delay: each step's draw is new, so after k steps the
    velocity error is bounded by sqrt(k) times one step's, 3.41 * 0.02 * 0.05 m/s = 3.41 mm/s; over the three steps of
    the window (1 + sqrt 2 + sqrt 3) * 3.41 mm/s * 0.3 s = 4.240 mm (piled up as a bias: 6.14 mm). An agent at rest
    with nothing sent, 3 cm from a wall, may approach at most 0.5 * (30 - 10 - 4.240) mm / 15 mm = 0.5253 v_max."""
    noisy = Disturbances(acting=Acting(force_noise=0.02), timing=Timing(action_delay=(2.0, 2.0)))
    bounds = FilterBounds.declared(noisy)
    one = math.sqrt(-2.0 * math.log(0.003)) * 0.02 * PUSH
    assert bounds.force_error * PUSH == pytest.approx(one, rel=1e-12) and bounds.horizon == 2
    error = sum(math.sqrt(k) * one for k in (1, 2, 3)) * DT
    assert error == pytest.approx(0.004240, abs=1e-6)
    gap = 0.03
    allowed = allowed_at_rest(bounds, gap)
    assert allowed == pytest.approx(GAMMA * (gap - MARGIN - error) / STEP, abs=1e-9)
    assert allowed == pytest.approx(0.5253, abs=1e-4)


def test_two_neighbours_position_errors_add_as_independent_draws() -> None:
    """Position noise 2 cm and drift 2 cm declared: one estimate's bound is 3.41 * 2.83 cm = 9.64 cm, the offset
    between two agents' estimates 3.41 * sqrt(2) * 2.83 cm = 13.63 cm (twice one's bound would be 19.28 cm). A ring
    neighbour straight ahead at 0.6 m: the agent may approach it at most 0.5 * gamma * (0.6 - 0.4 - 0.01 - 0.1363) m
    / 15 mm = 0.8943 v_max (each agent takes half of a shared barrier)."""
    sensing = Disturbances(sensing=Sensing(position_noise=0.02, position_drift=0.02))
    bounds = FilterBounds.declared(sensing)
    deviation = math.hypot(0.02, 0.02)
    tail = math.sqrt(-2.0 * math.log(0.003))
    assert bounds.position_error == pytest.approx(tail * deviation, rel=1e-12)
    assert bounds.neighbour_offset_error == pytest.approx(tail * math.sqrt(2.0) * deviation, rel=1e-12)
    assert tail == pytest.approx(3.4086, abs=1e-4) and bounds.neighbour_offset_error == pytest.approx(0.13634, abs=1e-5)
    assert FilterBounds(position_error=0.05).neighbour_offset_error == 0.1  # a hard bound: both at it, opposite ways
    row = np.zeros(ROW_SIZE)
    row[LAYOUT["lidar_obstacles"]] = row[LAYOUT["lidar_agents"]] = 1.0
    row[LAYOUT["neighbour_offsets"]] = [0.6, 0.0, -0.8, -0.8]
    allowed = allowed_speed(SafetyFilter(CONFIG, bounds=bounds), row)
    expected = 0.5 * GAMMA * (0.6 - 2 * RADIUS - MARGIN - bounds.neighbour_offset_error) / STEP
    assert allowed == pytest.approx(expected, abs=1e-9) and allowed == pytest.approx(0.8943, abs=1e-4)


# 5. The ideal filter is unchanged ---------------------------------------------------------------------------------------


def test_ideal_disturbances_declare_no_bound() -> None:
    """``FilterBounds.declared(Disturbances())`` is exact whatever the tail, predicts over no delay, and is what a
    filter of the ideal task takes by default; the shipped profiles declare the bounds their files give."""
    for tail in (1.0, 2.0, 10.0):
        declared = FilterBounds.declared(Disturbances(), tail=tail)
        assert declared == FilterBounds() and declared.is_exact and declared.horizon == 0
    assert SafetyFilter(CONFIG).bounds == FilterBounds()
    harsh = FilterBounds.declared(profile("harsh"))
    assert harsh.range_error == pytest.approx(0.09) and harsh.delay == (0.0, 5.0) and harsh.gain == (0.75, 1.25)
    assert harsh.horizon == 5 and harsh.fill_dropped and not harsh.is_exact


def test_the_ideal_filter_is_the_exact_one_bit_for_bit() -> None:
    """On engine rows of every scene family (squeezed so that most actions are changed), with random actions, a filter
    of the ideal task and one built with ``bounds=FilterBounds()`` give the same actions and reports bit for bit, and
    the actions an ideal filter is given as sent change nothing."""
    rng = np.random.default_rng(0)
    changed = 0
    for scenes in SCENES:
        config = CONFIG.replace(scenes=scenes)
        engine = FormationEngine([config])
        rows = engine.reset(0, seed=11).astype(np.float64)
        rows[:, LAYOUT["lidar_obstacles"]] *= 0.02
        rows[:, LAYOUT["velocity"]] = rng.uniform(-1, 1, (len(rows), 2)) * V_MAX / 2
        default, exact = SafetyFilter(config), SafetyFilter(config, bounds=FilterBounds())
        for dtype in (np.float32, np.float64):
            actions = rng.uniform(-1, 1, (len(rows), 2)).astype(dtype)
            first, first_report = default.filter(rows, actions)
            second, second_report = exact.filter(rows, actions)
            third, _ = exact.filter(rows, actions, rng.uniform(-1, 1, (len(rows), 3, 2)))
            assert first.dtype == dtype and first.tobytes() == second.tobytes() == third.tobytes()
            for name in ("changed", "change", "infeasible", "separation"):
                assert getattr(first_report, name).tobytes() == getattr(second_report, name).tobytes()
            changed += int(first_report.changed.sum())
    assert changed > 30


class Pusher(Policy):
    """Every agent proposes a full-speed action along +x."""

    def __init__(self, config: FormationConfig) -> None:
        self.config = config

    def _agent_step(
        self,
        observations: np.ndarray,
        agents: np.ndarray,
        state: Any,
        episode_start: np.ndarray | None,
        received: np.ndarray | None,
        deterministic: bool,
    ) -> AgentStep:
        return AgentStep(np.tile(np.array([1.0, 0.0], dtype=np.float32), (len(observations), 1)), state, None)

    def fit(self, config: FormationConfig) -> Policy:
        return Pusher(config)


def test_a_safe_policy_keeps_what_its_agents_sent() -> None:
    """A :class:`SafePolicy` of a delayed task declares the delay and passes the actions its agents sent to the filter:
    over a delayed episode its actions are those of a :class:`SafetyFilter` with :class:`SentCommands` kept by hand,
    and an episode start forgets them."""
    config = SMALL.replace(disturbances=DELAYED)
    engine = FormationEngine([config])
    positions = np.array([[SMALL.world_width - RADIUS - 0.08, 5.0], [SMALL.world_width - RADIUS - 0.1, 6.0], [9.0, 4.0]])
    rows = engine.reset(0, seed=0, scenario=Scenario(positions, np.array([3.0, 5.0])))
    safe_policy = SafePolicy(Pusher(config))
    assert safe_policy.filter.bounds == FilterBounds.declared(DELAYED) and safe_policy.sent.horizon == 2
    safety, sent = SafetyFilter(config), SentCommands(2)
    starts = np.ones(3, dtype=bool)
    braked = 0
    for _ in range(12):
        actions, _ = safe_policy.predict(rows, None, starts)
        expected, report = safety.filter(rows, np.tile([1.0, 0.0], (3, 1)).astype(np.float32), sent.rows(3, starts))
        sent.add(expected)
        assert np.array_equal(actions, expected)
        braked += int(report.changed.sum())
        starts[:] = False
        rows = engine.step(actions).observations
    assert braked > 0
    assert safe_policy.sent.actions.any() and not safe_policy.sent.rows(3, np.ones(3, dtype=bool)).any()
