"""Tests of the reward terms (eqs 21-42), their per-step assembly, weighting and clipping."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sb3_formation.env.config import REWARD_TERMS, FormationConfig
from sb3_formation.env.geometry import measure_formation, reference_bearings, reference_polygon, ring_neighbours
from sb3_formation.env.rewards import (
    TERM_ROW,
    angle_between,
    angle_term,
    bearing_term,
    centroid_term,
    collision_term,
    combine_rewards,
    distance_term,
    goal_term,
    nearest_gaps,
    reward_terms,
    time_term,
)

PI = math.pi
ALL_FLY = np.ones(8, dtype=bool)  # every agent flies
NO_WALLS = np.zeros((0, 5))


def vec(x: float, y: float) -> np.ndarray:
    """A 2-D float vector."""
    return np.array([x, y], dtype=float)


# Single terms --------------------------------------------------------------------------------------------------


def test_time_term() -> None:
    """Eq. 33: r_late exactly on step T_s, 0 before."""
    assert time_term(2500, 2500, -10.0) == -10.0
    assert time_term(2499, 2500, -10.0) == 0.0
    assert time_term(1, 2500, -10.0) == 0.0


@pytest.mark.parametrize(("error", "expected"), [(-30.0, -1.0), (15.0, -0.5), (0.0, 0.0), (-240.0, -8.0)])
def test_angle_term(error: float, expected: float) -> None:
    """Eq. 34: -|error| / 30 (e.g. -|-30|/30 = -1, -15/30 = -0.5, -240/30 = -8)."""
    assert angle_term(error, 30.0) == pytest.approx(expected, abs=1e-12)


def test_bearing_term() -> None:
    """Eq. 35: -0.5 * (0.2 + 0.4) / 2 = -0.15; two errors of 2 give the minimum -1."""
    assert bearing_term(np.array([0.2, 0.4])) == pytest.approx(-0.15, abs=1e-12)
    assert bearing_term(np.array([2.0, 2.0])) == pytest.approx(-1.0, abs=1e-12)
    assert bearing_term(np.array([0.0, 0.0])) == 0.0


def test_distance_term() -> None:
    """Eq. 36: only the excess over d_ref counts: -(max(1.7 - 1.5, 0) + max(1.2 - 1.5, 0)) / 2 / 0.1 = -1."""
    assert distance_term(np.array([1.7, 1.2]), 1.5, 0.1) == pytest.approx(-1.0, abs=1e-12)
    # -(0.3 + 0.5) / 2 / 0.1 = -4
    assert distance_term(np.array([1.8, 2.0]), 1.5, 0.1) == pytest.approx(-4.0, abs=1e-12)
    assert distance_term(np.array([1.5, 0.4]), 1.5, 0.1) == 0.0


def test_centroid_term() -> None:
    """Eq. 37: r_c within eta_c (inclusive), else 0."""
    assert centroid_term(1.0, 1.2, 0.01) == 0.01
    assert centroid_term(1.2, 1.2, 0.01) == 0.01
    assert centroid_term(1.21, 1.2, 0.01) == 0.0


def test_goal_term_progress() -> None:
    """Eq. 38 with v_max = 0.05, dt = 0.3 (full-speed step 0.015 m): k1 + progress / 0.015."""
    # 0.015 m closer: -1.1 + 0.015 / 0.015 = -0.1
    assert goal_term(3.0, 2.985, 2.985, 0.4, 4.0, -1.1, 0.3, 0.05) == pytest.approx(-0.1, abs=1e-9)
    # 0.0075 m further: -1.1 - 0.0075 / 0.015 = -1.6
    assert goal_term(3.0, 3.0075, 3.0075, 0.4, 4.0, -1.1, 0.3, 0.05) == pytest.approx(-1.6, abs=1e-9)
    # no progress: k1
    assert goal_term(3.0, 3.0, 3.0, 0.4, 4.0, -1.1, 0.3, 0.05) == pytest.approx(-1.1, abs=1e-12)


def test_goal_term_reached() -> None:
    """Eq. 38: r_reached once the centroid is within eta_g (inclusive), whatever the progress."""
    assert goal_term(0.5, 0.3, 0.3, 0.4, 4.0, -1.1, 0.3, 0.05) == 4.0
    assert goal_term(0.41, 0.4, 0.4, 0.4, 4.0, -1.1, 0.3, 0.05) == 4.0
    assert goal_term(0.42, 0.41, 0.41, 0.4, 4.0, -1.1, 0.3, 0.05) == pytest.approx(-1.1 + 0.01 / 0.015, abs=1e-9)


def test_goal_term_rewards_the_way_round_and_pays_on_the_straight_distance() -> None:
    """goal_progress: geodesic: progress is the way's decrease (here 6.0 -> 5.985 m while the straight distance, 2 m,
    grows), and r_reached is paid once the straight distance is within eta_g, whatever the way."""
    assert goal_term(6.0, 5.985, 2.0, 0.4, 4.0, -1.1, 0.3, 0.05) == pytest.approx(-0.1, abs=1e-9)
    assert goal_term(1.0, 0.99, 0.39, 0.4, 4.0, -1.1, 0.3, 0.05) == 4.0


@pytest.mark.parametrize(
    ("agent", "obstacle", "expected"), [(True, True, -1.0), (True, False, -1.0), (False, True, -5.0), (False, False, 0.0)]
)
def test_collision_term(agent: bool, obstacle: bool, expected: float) -> None:
    """Eq. 39: r_j for agent contact takes priority over r_o for an obstacle within d_safe."""
    assert collision_term(agent, obstacle, -1.0, -5.0) == expected


@pytest.mark.parametrize(
    ("first", "second", "expected"),
    [
        ((1.0, 0.0), (-2.0, 0.0), PI),
        ((0.0, 0.05), (0.0, -0.01), PI),
        ((1.0, 0.0), (0.0, 3.0), PI / 2),
        ((1.0, 0.0), (0.0, -3.0), PI / 2),
        ((0.02, 0.02), (0.04, 0.0), PI / 4),
        ((0.03, 0.0), (0.05, 0.0), 0.0),
        ((0.0, 0.0), (1.0, 0.0), 0.0),
        ((1.0, 0.0), (-1e-6, 0.0), 0.0),  # speed 1e-6 counts as still
        ((-1e-6, 0.0), (1.0, 0.0), 0.0),
        ((2e-6, 0.0), (-1.0, 0.0), PI),  # just above the still speed
    ],
)
def test_angle_between(first: tuple[float, float], second: tuple[float, float], expected: float) -> None:
    """Unsigned angle in [0, pi]; 0 when either vector has speed <= 1e-6."""
    assert angle_between(vec(*first), vec(*second)) == pytest.approx(expected, abs=1e-12)


# Nearest gaps --------------------------------------------------------------------------------------------------


def test_nearest_gaps() -> None:
    """Centre distance to the nearest agent; surface gap to the nearest wall or obstacle (R = 0.2, 15 x 10 world).

    Obstacle (1, 3.2) r=0.5.
    Agent 0 (1,1): agents 1 m, 5 m, far -> 1; walls min(1, 14, 1, 9) - 0.2 = 0.8; obstacle 2.2 - 0.7 = 1.5 -> 0.8.
    Agent 1 (1,2): agents 1 m -> 1; walls 1 - 0.2 = 0.8; obstacle 1.2 - 0.7 = 0.5 -> 0.5.
    Agent 2 (4,5): agents hypot(3,3), 5, hypot(10.9, 4) -> hypot(3,3); walls 4 - 0.2 = 3.8;
        obstacle hypot(3, 1.8) - 0.7 = 2.798571 -> 2.798571.
    Agent 3 (14.9, 9): nearest agent agent 2, hypot(10.9, 4); wall 0.1 - 0.2 = -0.1 (sunk into the wall).
    """
    positions = np.array([[1.0, 1.0], [1.0, 2.0], [4.0, 5.0], [14.9, 9.0]])
    nearest_agent, nearest_obstacle = nearest_gaps(
        positions, 0.2, np.array([[1.0, 3.2, 0.5]]), NO_WALLS, 15.0, 10.0, np.ones(len(positions), bool)
    )
    np.testing.assert_allclose(nearest_agent, [1.0, 1.0, math.hypot(3, 3), math.hypot(10.9, 4)], rtol=1e-12)
    np.testing.assert_allclose(nearest_obstacle, [0.8, 0.5, math.hypot(3, 1.8) - 0.7, -0.1], atol=1e-12)
    assert nearest_obstacle[2] == pytest.approx(2.798571, abs=1e-6)


def test_nearest_gaps_without_obstacles_and_sunk_in() -> None:
    """No obstacles: the walls alone; an agent overlapping an obstacle has a negative gap (0.3 - 0.5 - 0.2 = -0.4)."""
    positions = np.array([[7.5, 0.5], [7.5, 9.7], [3.0, 5.0]])
    nearest_agent, nearest_obstacle = nearest_gaps(
        positions, 0.2, np.zeros((0, 3)), NO_WALLS, 15.0, 10.0, np.ones(len(positions), bool)
    )
    # walls: 0.5 - 0.2 = 0.3; 10 - 9.7 - 0.2 = 0.1; 3 - 0.2 = 2.8
    np.testing.assert_allclose(nearest_obstacle, [0.3, 0.1, 2.8], atol=1e-12)
    np.testing.assert_allclose(nearest_agent, [math.hypot(4.5, 4.5), math.hypot(4.5, 4.7), math.hypot(4.5, 4.5)])
    _, nearest_obstacle = nearest_gaps(
        positions, 0.2, np.array([[3.3, 5.0, 0.5]]), NO_WALLS, 15.0, 10.0, np.ones(len(positions), bool)
    )
    assert nearest_obstacle[2] == pytest.approx(-0.4, abs=1e-12)


def test_nearest_gaps_with_a_wall() -> None:
    """A wall from (5, 2) to (5, 8), 0.4 m thick (R = 0.2): agent (4, 5) is 1 - 0.2 - 0.2 = 0.6 from it; agent
    (5, 9) is past its end: hypot(0, 1) - 0.2 - 0.2 = 0.6 too, but the border above is nearer (10 - 9 - 0.2 = 0.8,
    not nearer): 0.6; agent (8, 8.5) is hypot(3, 0.5) - 0.4 = 2.6414 from the wall, 1.5 - 0.2 = 1.3 from the border."""
    positions = np.array([[4.0, 5.0], [5.0, 9.0], [8.0, 8.5]])
    wall = np.array([[5.0, 2.0, 5.0, 8.0, 0.4]])
    _, nearest_obstacle = nearest_gaps(positions, 0.2, np.zeros((0, 3)), wall, 15.0, 10.0, ALL_FLY[: len(positions)])
    np.testing.assert_allclose(nearest_obstacle, [0.6, 0.6, 1.3], atol=1e-12)


# reward_terms ----------------------------------------------------------------------------------------------------


def row(terms: np.ndarray, name: str) -> np.ndarray:
    """Row of term ``name``."""
    return terms[TERM_ROW[name]]


def test_term_rows_follow_reward_terms() -> None:
    """TERM_ROW maps every name of REWARD_TERMS to its position."""
    assert [TERM_ROW[name] for name in REWARD_TERMS] == list(range(len(REWARD_TERMS)))


# Six agents: previous velocities v_t and new velocities v_t+1 (m/s).
V_T = np.array([[0.05, 0.0], [0.05, 0.0], [0.0, 0.0], [-0.05, 0.0], [0.02, 0.02], [0.0, -0.05]])
V_T1 = np.array([[0.0, 0.05], [0.05, 0.0], [0.03, 0.03], [0.05, 0.0], [0.04, 0.0], [0.0, -0.01]])
# Eq. 40, -angle(v_t^i, v_t+1^i): 90 deg turn, none, still before, reversal, 45 deg turn, none.
MOVE = [-PI / 2, 0.0, 0.0, -PI, -PI / 4, 0.0]
# Eq. 41, -mean over j in (i-1, i+1) of angle(v_t+1^i, v_t^j):
# 0: (0,1) vs v_t^5 = (0,-1): pi, vs v_t^1 = (1,0): pi/2 -> -3pi/4
# 1: (1,0) vs v_t^0 = (1,0): 0, vs v_t^2 still: 0 -> 0
# 2: 45 deg vs v_t^1 (0 deg): pi/4, vs v_t^3 (180 deg): 3pi/4 -> -pi/2
# 3: (1,0) vs v_t^2 still: 0, vs v_t^4 (45 deg): pi/4 -> -pi/8
# 4: (1,0) vs v_t^3 (180 deg): pi, vs v_t^5 (270 deg): pi/2 -> -3pi/4
# 5: 270 deg vs v_t^4 (45 deg): 3pi/4, vs v_t^0 (0 deg): pi/2 -> -5pi/8
VELOCITY = [-3 * PI / 4, 0.0, -PI / 2, -PI / 8, -3 * PI / 4, -5 * PI / 8]
# Collisions: agent 2 touches an agent (0.4 = 2 R_a) and is near an obstacle -> r_j; agent 4 is 0.04 < d_safe = 0.05
# from an obstacle -> r_o = -5; agent 5 at exactly d_safe -> 0.
NEAREST_AGENT = np.array([1.6, 1.6, 0.4, 1.6, 1.6, 0.41])
NEAREST_OBSTACLE = np.array([1.0, 1.0, 0.01, 1.0, 0.04, 0.05])
COLL = [0.0, 0.0, -1.0, 0.0, -5.0, 0.0]


def mirrored_hexagon(radius: float) -> np.ndarray:
    """The reference hexagon reflected x -> -x, same agent order, centred at (5, 5)."""
    return reference_polygon(6, radius) * np.array([-1.0, 1.0]) + 5.0


def ch5_terms(step: int, radius: float = 1.6) -> np.ndarray:
    """reward_terms of ch5-bearing on the mirrored hexagon, 0.015 m of goal progress and the velocities above."""
    config = FormationConfig.task("ch5-bearing")
    neighbours = ring_neighbours(6)
    formation = measure_formation(mirrored_hexagon(radius), neighbours, reference_bearings(6), 120.0, config.d_ref)
    return reward_terms(config, step, formation, 5.0, 4.985, V_T, V_T1, neighbours, NEAREST_AGENT, NEAREST_OBSTACLE)


def test_reward_terms_individual_ch5() -> None:
    """ch5-bearing, mirrored hexagon of circumradius 1.6 (side 1.6), every term by hand."""
    terms = ch5_terms(step=10)
    assert terms.shape == (len(REWARD_TERMS), 6)
    np.testing.assert_allclose(row(terms, "time"), 0.0)
    # mirrored: beta = 240, |120 - 240| / 30 = 4
    np.testing.assert_allclose(row(terms, "angle"), -4.0, atol=1e-9)
    # mirrored bearing from i to i+1: u(180 - phi_i) vs u(phi_i), error 2|cos phi_i|, phi = 30, 90, ..., 330 deg:
    # errors sqrt(3), 0, sqrt(3), sqrt(3), 0, sqrt(3); agent i uses phi_{i-1} and phi_i: -0.5 * mean.
    s3 = math.sqrt(3.0)
    bearing = [-0.5 * (s3 + s3) / 2, -0.5 * s3 / 2, -0.5 * s3 / 2, -0.5 * (s3 + s3) / 2, -0.5 * s3 / 2, -0.5 * s3 / 2]
    np.testing.assert_allclose(row(terms, "bearing"), bearing, atol=1e-9)
    # side 1.6 > d_ref 1.5 on both sides: -(0.1 + 0.1) / 2 / 0.1 = -1
    np.testing.assert_allclose(row(terms, "dist"), -1.0, atol=1e-9)
    # every agent 1.6 m > eta_c = 1.2 m from the centroid
    np.testing.assert_allclose(row(terms, "centroid"), 0.0)
    # goal: -1.1 + (5.0 - 4.985) / (0.3 * 0.05) = -1.1 + 1 = -0.1, the same for everyone
    np.testing.assert_allclose(row(terms, "goal"), -0.1, atol=1e-9)
    np.testing.assert_allclose(row(terms, "move"), MOVE, atol=1e-12)
    np.testing.assert_allclose(row(terms, "velocity"), VELOCITY, atol=1e-12)
    np.testing.assert_allclose(row(terms, "coll"), COLL)


def test_reward_terms_small_regular_hexagon() -> None:
    """A regular hexagon of circumradius 1 (side 1 <= 1.5, all within eta_c): no shape or distance error, r_c each."""
    config = FormationConfig.task("ch5-bearing")
    neighbours = ring_neighbours(6)
    formation = measure_formation(reference_polygon(6, 1.0) + 5.0, neighbours, reference_bearings(6), 120.0, 1.5)
    terms = reward_terms(config, 3, formation, 5.0, 5.0, V_T, V_T1, neighbours, NEAREST_AGENT, NEAREST_OBSTACLE)
    for name in ("angle", "bearing", "dist"):
        np.testing.assert_allclose(row(terms, name), 0.0, atol=1e-9)
    np.testing.assert_allclose(row(terms, "centroid"), 0.01)
    np.testing.assert_allclose(row(terms, "goal"), -1.1, atol=1e-12)  # no progress: k1


def test_reward_terms_time_at_max_steps() -> None:
    """r_late = -10 for every agent exactly at step == max_steps = 2500, 0 one step before."""
    np.testing.assert_array_equal(row(ch5_terms(step=2500), "time"), -10.0)
    np.testing.assert_array_equal(row(ch5_terms(step=2499), "time"), 0.0)


def ch4_team_terms(
    nearest_agent: list[float], nearest_obstacle: list[float], goal_distance: float = 0.5, team: bool = True
) -> np.ndarray:
    """reward_terms of ch4-team (n = 3) on the right triangle (0,0), (2,0), (0,2) shifted to (5,5)."""
    config = FormationConfig.task("ch4-team" if team else "ch4-individual")
    neighbours = ring_neighbours(3)
    positions = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 2.0]]) + 5.0
    formation = measure_formation(positions, neighbours, reference_bearings(3), 60.0, config.d_ref)
    v_t = np.array([[0.05, 0.0], [0.0, 0.05], [0.0, 0.0]])
    v_t1 = np.array([[0.0, 0.05], [0.0, 0.05], [-0.05, 0.0]])
    return reward_terms(
        config, 5, formation, 0.6, goal_distance, v_t, v_t1, neighbours, np.array(nearest_agent), np.array(nearest_obstacle)
    )


# Per-agent values of the ch4 triangle (0,0), (2,0), (0,2), by hand:
# beta = 90, 45, 45 -> angle terms -30/30, -15/30, -15/30 = -1, -0.5, -0.5.
CH4_ANGLE = [-1.0, -0.5, -0.5]
# bearing errors (see test_geometry's right triangle): 2 sin 15 and 1; 1 and 2 sin 22.5; 2 sin 22.5 and 2 sin 15.
_S15, _S22 = 2 * math.sin(math.radians(15)), 2 * math.sin(math.radians(22.5))
CH4_BEARING = [-0.5 * (_S15 + 1) / 2, -0.5 * (1 + _S22) / 2, -0.5 * (_S22 + _S15) / 2]
# sides 2, 2, 2 sqrt(2) = 2.828 vs d_ref 2.4, m_ref 0.1: 0, -(2.828 - 2.4)/2/0.1 twice
CH4_DIST = [0.0, -(2 * math.sqrt(2) - 2.4) / 0.2, -(2 * math.sqrt(2) - 2.4) / 0.2]
# centroid (2/3, 2/3): distances 2 sqrt(2)/3 = 0.943 <= 1.2, 2 sqrt(5)/3 = 1.491 twice -> r_c = 0.01, 0, 0
CH4_CENTROID = [0.01, 0.0, 0.0]
# move: 0 -> 90 deg turn; 1 straight; 2 was still -> -pi/2, 0, 0
CH4_MOVE = [-PI / 2, 0.0, 0.0]
# velocity (neighbours = the other two): 0: (0,1) vs v_t^2 still 0, vs v_t^1 (0,1) 0 -> 0;
# 1: (0,1) vs v_t^0 (1,0) pi/2, vs v_t^2 still 0 -> -pi/4; 2: (-1,0) vs v_t^1 (0,1) pi/2, vs v_t^0 (1,0) pi -> -3pi/4
CH4_VELOCITY = [0.0, -PI / 4, -3 * PI / 4]


def test_reward_terms_ch4_individual() -> None:
    """ch4-individual: per-agent terms as computed by hand, goal reached (0.5 <= eta_g = 0.5): r_reached = 9."""
    terms = ch4_team_terms([2.0, 0.4, 2.0], [1.0, 1.0, 0.01], team=False)
    np.testing.assert_allclose(row(terms, "angle"), CH4_ANGLE, atol=1e-9)
    np.testing.assert_allclose(row(terms, "bearing"), CH4_BEARING, atol=1e-9)
    np.testing.assert_allclose(row(terms, "dist"), CH4_DIST, atol=1e-9)
    np.testing.assert_allclose(row(terms, "centroid"), CH4_CENTROID)
    np.testing.assert_allclose(row(terms, "move"), CH4_MOVE, atol=1e-12)
    np.testing.assert_allclose(row(terms, "velocity"), CH4_VELOCITY, atol=1e-12)
    np.testing.assert_allclose(row(terms, "goal"), 9.0)
    # agent 1 touches an agent: r_j = -1; agent 2 is 0.01 < d_safe = 0.02 from an obstacle: r_o = -6
    np.testing.assert_allclose(row(terms, "coll"), [0.0, -1.0, -6.0])


def test_reward_terms_ch4_team_means() -> None:
    """ch4-team: every agent receives the team mean of each per-agent term (eqs 28-31)."""
    terms = ch4_team_terms([2.0, 2.0, 2.0], [1.0, 1.0, 1.0])
    assert terms.shape == (len(REWARD_TERMS), 3)
    # angle: (-1 - 0.5 - 0.5) / 3 = -2/3
    np.testing.assert_allclose(row(terms, "angle"), -2.0 / 3.0, atol=1e-9)
    # bearing: -0.5 * (sum of the six errors) / 6 = -(2 + 4 sin 15 + 4 sin 22.5) / 12 ... written as 2 sin terms
    np.testing.assert_allclose(row(terms, "bearing"), -(2 + 2 * _S15 + 2 * _S22) / 12, atol=1e-9)
    np.testing.assert_allclose(row(terms, "bearing"), sum(CH4_BEARING) / 3, atol=1e-9)
    # dist: -2 * (2 sqrt(2) - 2.4) / 0.2 / 3 = -1.428
    np.testing.assert_allclose(row(terms, "dist"), -2 * (2 * math.sqrt(2) - 2.4) / 0.2 / 3, atol=1e-9)
    np.testing.assert_allclose(row(terms, "centroid"), 0.01 / 3, atol=1e-12)
    np.testing.assert_allclose(row(terms, "move"), -PI / 6, atol=1e-12)  # (-pi/2 + 0 + 0) / 3
    np.testing.assert_allclose(row(terms, "velocity"), -PI / 3, atol=1e-12)  # (0 - pi/4 - 3pi/4) / 3
    np.testing.assert_allclose(row(terms, "goal"), 9.0)
    np.testing.assert_allclose(row(terms, "time"), 0.0)
    np.testing.assert_allclose(row(terms, "coll"), 0.0)


@pytest.mark.parametrize(
    ("nearest_agent", "nearest_obstacle", "expected"),
    [
        ([2.0, 0.4, 2.0], [1.0, 1.0, 1.0], -1.0),  # agent 1 touches (0.4 = 2 R_a): r_j for everyone
        ([2.0, 0.39, 2.0], [1.0, 1.0, 0.0], -1.0),  # contact and obstacle: r_j has priority
        ([2.0, 2.0, 0.41], [1.0, 0.01, 1.0], -6.0),  # no contact (0.41 > 0.4); agent 1 within d_safe: r_o
        ([2.0, 2.0, 2.0], [0.02, 1.0, 1.0], 0.0),  # gap exactly d_safe = 0.02 is not closer
    ],
)
def test_reward_terms_ch4_team_collision(nearest_agent: list[float], nearest_obstacle: list[float], expected: float) -> None:
    """Eq. 31: the team collision term is r_j if any two agents touch, else r_o if any agent is within d_safe."""
    np.testing.assert_array_equal(row(ch4_team_terms(nearest_agent, nearest_obstacle), "coll"), expected)


def test_reward_terms_ch4_team_goal_progress() -> None:
    """ch4-team, goal not reached: -1.1 + (0.6 - 0.585) / 0.015 = -0.1 for every agent."""
    terms = ch4_team_terms([2.0, 2.0, 2.0], [1.0, 1.0, 1.0], goal_distance=0.585)
    np.testing.assert_allclose(row(terms, "goal"), -0.1, atol=1e-9)


# combine_rewards ------------------------------------------------------------------------------------------------


def coefficient_vector(coefficients: dict[str, float]) -> np.ndarray:
    """The coefficients dict as an array in REWARD_TERMS order."""
    return np.array([coefficients[name] for name in REWARD_TERMS])


def test_combine_rewards_weighted_sum() -> None:
    """ch5-bearing stage-3 weights: 1 time, 0 angle, 0.3 bearing, 1 dist, 1 centroid, 0.5 goal, 0.3 move, 0.1 vel,
    0.5 coll.

    Agent 0: 0 + 0 * -1 + 0.3 * -0.2 + -1 + 0.01 + 0.5 * -0.1 + 0.3 * -0.5 + 0.1 * -1 + 0.5 * -1
        = -0.06 - 1 + 0.01 - 0.05 - 0.15 - 0.1 - 0.5 = -1.85.
    Agent 1: -10 + 0.3 * -0.5 + -5 + 0.5 * -5 = -17.65 -> clipped to -10.
    Agent 2: 0.5 * 4 + 0.01 = 2.01.
    """
    weights = coefficient_vector(FormationConfig.task("ch5-bearing").reward_coefficients(3))
    columns = {
        "time": [0.0, -10.0, 0.0],
        "angle": [-1.0, 0.0, 0.0],
        "bearing": [-0.2, 0.0, 0.0],
        "dist": [-1.0, -5.0, 0.0],
        "centroid": [0.01, 0.0, 0.01],
        "goal": [-0.1, 0.0, 4.0],
        "move": [-0.5, -0.5, 0.0],
        "velocity": [-1.0, 0.0, 0.0],
        "coll": [-1.0, -5.0, 0.0],
    }
    terms = np.array([columns[name] for name in REWARD_TERMS])
    np.testing.assert_allclose(combine_rewards(terms, weights, 10.0), [-1.85, -10.0, 2.01], atol=1e-12)


def test_combine_rewards_clipping() -> None:
    """Unit weights: sums 12, -12, 3, 10.5 clip to 10, -10, 3, 10; with clip 5: 5, -5, 3, 5."""
    terms = np.zeros((len(REWARD_TERMS), 4))
    terms[TERM_ROW["goal"]] = [9.0, -6.0, 1.0, 10.0]
    terms[TERM_ROW["coll"]] = [3.0, -6.0, 2.0, 0.5]
    ones = np.ones(len(REWARD_TERMS))
    np.testing.assert_allclose(combine_rewards(terms, ones, 10.0), [10.0, -10.0, 3.0, 10.0])
    np.testing.assert_allclose(combine_rewards(terms, ones, 5.0), [5.0, -5.0, 3.0, 5.0])
    # a zero weight switches a term off: goal only -> 9, -6, 1, 10
    goal_only = np.zeros(len(REWARD_TERMS))
    goal_only[TERM_ROW["goal"]] = 1.0
    np.testing.assert_allclose(combine_rewards(terms, goal_only, 10.0), [9.0, -6.0, 1.0, 10.0])
