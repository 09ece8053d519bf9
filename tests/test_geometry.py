"""Tests of the formation geometry: ring neighbours, reference bearings, angles, errors and flags."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sb3_formation.env.geometry import measure_formation, reference_bearings, reference_polygon, ring_neighbours

D_REF = 1.5
OFFSET = np.array([5.0, 4.0])


def unit(x: float, y: float) -> tuple[float, float]:
    """(x, y) scaled to unit length (plain math, independent of the package)."""
    length = math.hypot(x, y)
    return x / length, y / length


def measure(positions: np.ndarray, beta_ref: float, d_ref: float = D_REF):
    """measure_formation with the ring neighbours and reference bearings of len(positions) agents."""
    n = len(positions)
    return measure_formation(positions, ring_neighbours(n), reference_bearings(n), beta_ref, d_ref)


def test_ring_neighbours_three() -> None:
    """n = 3: each agent's neighbours are the other two, preceding first."""
    np.testing.assert_array_equal(ring_neighbours(3), [[2, 1], [0, 2], [1, 0]])


def test_ring_neighbours_six() -> None:
    """n = 6: agent i's neighbours are i - 1 and i + 1 modulo 6 (agent 0: 5 and 1)."""
    expected = [[5, 1], [0, 2], [1, 3], [2, 4], [3, 5], [4, 0]]
    neighbours = ring_neighbours(6)
    assert neighbours.shape == (6, 2)
    np.testing.assert_array_equal(neighbours, expected)


def test_reference_bearings_match_table_5_2() -> None:
    """reference_bearings(6) is Table 5.2 of the thesis, each vector normalised (d = sqrt(3))."""
    d = math.sqrt(3.0)
    # Table 5.2, (preceding, succeeding) per agent 1..6 (agent index 0..5); every vector has length 2/sqrt(3).
    table = [
        [(-1.0, 1.0 / d), (1.0, 1.0 / d)],
        [(-1.0, -1.0 / d), (0.0, 2.0 / d)],
        [(0.0, -2.0 / d), (-1.0, 1.0 / d)],
        [(1.0, -1.0 / d), (-1.0, -1.0 / d)],
        [(1.0, 1.0 / d), (0.0, -2.0 / d)],
        [(0.0, 2.0 / d), (1.0, -1.0 / d)],
    ]
    expected = np.array([[unit(*vector) for vector in row] for row in table])
    bearings = reference_bearings(6)
    assert bearings.shape == (6, 2, 2)
    np.testing.assert_allclose(bearings, expected, atol=1e-12)


@pytest.mark.parametrize("n", [3, 4, 5, 7])
def test_reference_bearings_are_unit_vectors(n: int) -> None:
    """Every reference bearing has length 1."""
    bearings = reference_bearings(n)
    assert bearings.shape == (n, 2, 2)
    lengths = [math.hypot(x, y) for x, y in bearings.reshape(-1, 2)]
    np.testing.assert_allclose(lengths, 1.0, atol=1e-12)


@pytest.mark.parametrize("n", [3, 4, 5, 7])
def test_reference_bearings_preceding_is_minus_previous_succeeding(n: int) -> None:
    """The bearing from i to i - 1 is minus the bearing from i - 1 to i, and i -> i + 1 is at 180/n + i * 360/n deg."""
    bearings = reference_bearings(n)
    for i in range(n):
        phi = math.radians(180.0 / n + i * 360.0 / n)
        np.testing.assert_allclose(bearings[i, 1], [math.cos(phi), math.sin(phi)], atol=1e-12)
        np.testing.assert_allclose(bearings[i, 0], -bearings[(i - 1) % n, 1], atol=1e-12)


# n, circumradius, interior angle (n - 2) * 180 / n, side 2 r sin(pi/n), side <= D_REF = 1.5
REGULAR_CASES = [
    (3, 1.0, 60.0, math.sqrt(3.0), False),  # side 2 * 1 * sin(60) = sqrt(3) = 1.732 > 1.5
    (3, 0.8, 60.0, 0.8 * math.sqrt(3.0), True),  # side 1.386 <= 1.5
    (4, 1.0, 90.0, math.sqrt(2.0), True),  # side 2 * sin(45) = sqrt(2) = 1.414 <= 1.5
    (6, 1.0, 120.0, 1.0, True),  # side 2 * sin(30) = 1
    (6, 1.6, 120.0, 1.6, False),  # side 1.6 > 1.5
]


@pytest.mark.parametrize(("n", "radius", "interior", "side", "in_range"), REGULAR_CASES)
def test_regular_polygon(n: int, radius: float, interior: float, side: float, in_range: bool) -> None:
    """The reference n-gon has no angle or bearing error, equal sides, and every vertex r from the centroid."""
    positions = reference_polygon(n, radius) + OFFSET
    state = measure(positions, interior)
    np.testing.assert_allclose(state.angles_deg, interior, atol=1e-9)
    np.testing.assert_allclose(state.angle_errors_deg, 0.0, atol=1e-9)
    np.testing.assert_allclose(state.bearing_errors, 0.0, atol=1e-9)
    np.testing.assert_allclose(state.neighbour_distances, side, rtol=1e-12)
    np.testing.assert_allclose(state.centroid, OFFSET, atol=1e-12)
    np.testing.assert_allclose(state.centroid_distances, radius, rtol=1e-12)
    assert state.orientation_flags.dtype == bool
    assert state.orientation_flags.all()
    assert state.range_flag is in_range


@pytest.mark.parametrize("n", [3, 4, 6])
def test_regular_polygon_offsets_and_bearings(n: int) -> None:
    """Offsets are p^j - p^i and bearings their unit vectors, computed here point by point."""
    positions = reference_polygon(n, 1.0) + OFFSET
    state = measure(positions, (n - 2) * 180.0 / n)
    for i in range(n):
        for slot, j in enumerate(((i - 1) % n, (i + 1) % n)):
            dx, dy = positions[j, 0] - positions[i, 0], positions[j, 1] - positions[i, 1]
            np.testing.assert_allclose(state.neighbour_offsets[i, slot], [dx, dy], atol=1e-12)
            np.testing.assert_allclose(state.bearings[i, slot], unit(dx, dy), atol=1e-12)


def test_reference_polygon_vertices() -> None:
    """reference_polygon(4, 2): vertex i at angle i * 90 - 90 deg, radius 2: (0,-2), (2,0), (0,2), (-2,0)."""
    np.testing.assert_allclose(reference_polygon(4, 2.0), [[0, -2], [2, 0], [0, 2], [-2, 0]], atol=1e-12)


# n, interior angle, mirrored beta = 360 - interior, |error| = 360 - 2 * interior
MIRROR_CASES = [(3, 60.0, 300.0, 240.0), (4, 90.0, 270.0, 180.0), (6, 120.0, 240.0, 120.0)]


@pytest.mark.parametrize(("n", "interior", "beta", "error"), MIRROR_CASES)
def test_mirrored_polygon(n: int, interior: float, beta: float, error: float) -> None:
    """Reflecting x -> -x (same agent order) turns every beta into 360 - interior and clears the orientation flags."""
    positions = reference_polygon(n, 1.0) * np.array([-1.0, 1.0]) + OFFSET
    state = measure(positions, interior)
    np.testing.assert_allclose(state.angles_deg, beta, atol=1e-9)
    np.testing.assert_allclose(np.abs(state.angle_errors_deg), error, atol=1e-9)
    assert not state.orientation_flags.any()


def test_mirrored_square_bearing_errors() -> None:
    """Mirrored square: reference bearing angle phi becomes 180 - phi; |u(phi) - u(180 - phi)| = 2|cos phi| = sqrt(2)."""
    positions = reference_polygon(4, 1.0) * np.array([-1.0, 1.0]) + OFFSET
    state = measure(positions, 90.0)
    # phi in {45, 135, 225, 315}: 2 |cos phi| = 2 * sqrt(2)/2 = sqrt(2) for every bearing
    np.testing.assert_allclose(state.bearing_errors, math.sqrt(2.0), atol=1e-12)


def test_right_triangle() -> None:
    """Agents (0,0), (1,0), (0,1): beta = 90, 45, 45 deg, computed by hand.

    Agent 0: to succeeding (1,0) at 0 deg, to preceding (0,1) at 90 deg -> beta = 90 - 0 = 90.
    Agent 1: to succeeding (-1,1) at 135 deg, to preceding (-1,0) at 180 deg -> beta = 180 - 135 = 45.
    Agent 2: to succeeding (0,-1) at 270 deg, to preceding (1,-1) at 315 deg -> beta = 315 - 270 = 45.
    """
    positions = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]) + OFFSET
    state = measure(positions, 60.0)
    np.testing.assert_allclose(state.angles_deg, [90.0, 45.0, 45.0], atol=1e-9)
    np.testing.assert_allclose(state.angle_errors_deg, [60.0 - 90.0, 60.0 - 45.0, 60.0 - 45.0], atol=1e-9)
    assert state.orientation_flags.all()
    r2 = math.sqrt(2.0)
    np.testing.assert_allclose(state.neighbour_distances, [[1.0, 1.0], [1.0, r2], [r2, 1.0]], rtol=1e-12)
    np.testing.assert_allclose(
        state.bearings,
        [[[0.0, 1.0], [1.0, 0.0]], [[-1.0, 0.0], [-1 / r2, 1 / r2]], [[1 / r2, -1 / r2], [0.0, -1.0]]],
        atol=1e-12,
    )
    # centroid (1/3, 1/3): distances sqrt(2)/3, sqrt((2/3)^2 + (1/3)^2) = sqrt(5)/3 twice
    np.testing.assert_allclose(state.centroid, OFFSET + 1.0 / 3.0, atol=1e-12)
    np.testing.assert_allclose(state.centroid_distances, [r2 / 3, math.sqrt(5) / 3, math.sqrt(5) / 3], rtol=1e-12)
    # Reference bearings of the triangle: i -> i+1 at 60, 180, 300 deg; i -> i-1 at 120, 240, 0 deg.
    # |u(a) - u(b)| = 2 sin(|a - b| / 2): agent 0: 120 vs 90, 60 vs 0; agent 1: 240 vs 180, 180 vs 135;
    # agent 2: 0 vs 315, 300 vs 270.
    s15, s30, s22 = 2 * math.sin(math.radians(15)), 2 * math.sin(math.radians(30)), 2 * math.sin(math.radians(22.5))
    np.testing.assert_allclose(state.bearing_errors, [[s15, s30], [s30, s22], [s22, s15]], atol=1e-12)


def test_reflex_angle_flag() -> None:
    """A dented quadrilateral: the dent's beta is reflex (> 180 deg) and only its orientation flag is False.

    Agent 3 at (1, 0.5): to preceding (2, 2) is atan2(1.5, 1) = 56.31 deg; to succeeding (0, 0) is
    180 + atan2(0.5, 1) = 206.57 deg; beta = (56.31 - 206.57) mod 360 = 209.74 deg.
    """
    positions = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [1.0, 0.5]])
    state = measure(positions, 90.0, d_ref=3.0)
    dent = (math.degrees(math.atan2(1.5, 1.0)) - (180.0 + math.degrees(math.atan2(0.5, 1.0)))) % 360.0
    assert dent == pytest.approx(209.7449, abs=1e-4)
    assert state.angles_deg[3] == pytest.approx(dent, abs=1e-9)
    # agent 0: to succeeding (2,0) at 0 deg, to preceding (1,0.5) at atan2(0.5, 1) = 26.57 deg
    assert state.angles_deg[0] == pytest.approx(math.degrees(math.atan2(0.5, 1.0)), abs=1e-9)
    np.testing.assert_array_equal(state.orientation_flags, [True, True, True, False])
    # the four angles of a simple quadrilateral traversed anti-clockwise sum to 360
    assert state.angles_deg.sum() == pytest.approx(360.0, abs=1e-9)


@pytest.mark.parametrize(("d_ref", "in_range"), [(1.2, False), (1.5, True), (math.sqrt(2.0), True), (1.0, False)])
def test_range_flag(d_ref: float, in_range: bool) -> None:
    """Right triangle with sides 1, 1, sqrt(2): in range iff sqrt(2) <= d_ref."""
    positions = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    assert measure(positions, 60.0, d_ref=d_ref).range_flag is in_range


def test_range_flag_one_long_side() -> None:
    """A unit square with one vertex pushed out: one side of length 1.3 exceeds d_ref = 1.25, the others do not."""
    positions = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.3]])
    # sides: 1, 1, |(-1, 0.3)| = 1.044, 1.3
    assert not measure(positions, 90.0, d_ref=1.25).range_flag
    assert measure(positions, 90.0, d_ref=1.3).range_flag
