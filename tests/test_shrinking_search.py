"""The shrinking controller's wall search: its begin, legs, dead end and rounding against hand-computed cases, the
agreement of a team's agents, and the cow-path bound on a straight wall."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sb3_formation.controllers import ShrinkingController
from sb3_formation.controllers.shrinking import MEMORY_FIELDS
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.formation_env import FormationEnv

CH5 = FormationConfig.task("ch5-bearing", stage=3)  # v_max 0.05 m/s, dt 0.3 s
COLUMN = {name: index for index, name in enumerate(MEMORY_FIELDS)}


def state(controller: ShrinkingController, **values: float) -> np.ndarray:
    """One started agent's memory with ``values`` by field name (angles in degrees where the name says ``phi``/``peak``)."""
    row = controller.initial_memory(1)
    row[0, COLUMN["started"]] = 1.0
    for name, value in values.items():
        row[0, COLUMN[name]] = math.radians(value) if name in ("phi", "peak") else value
    return row


def detour(controller: ShrinkingController, **values: float) -> np.ndarray:
    """A detour under way: hit 5 m from the goal at c_g = (5, 0) on a wall whose normal (into it) is +x, on the
    anticlockwise side; the last step went freely (progress 1) with the heading on the goal."""
    hit = {"hit": 5.0, "hit_x": -5.0, "hit_y": 0.0, "shortfall_x": 1.0, "sigma": 1.0, "heading_x": 1.0}
    return state(controller, **{**hit, **values})


def degrees(row: np.ndarray, name: str) -> float:
    return math.degrees(row[0, COLUMN[name]])


def test_a_detour_begins_after_patience_turned_to_the_drift_side() -> None:
    """Stuck (the step made nothing of h = (1, 0)): the shortfall's mean moves a = 0.1 of the way to h - 0 = (1, 0);
    after ``patience`` blocked steps the side is the drift's (right: sigma = -1), the heading turns 60 deg at once, and
    the hit point is -c_g."""
    controller = ShrinkingController(CH5, patience=3)
    row = state(controller, heading_x=1.0, progress=0.2, lateral=-0.3, waited=2.0, shortfall_x=0.8, closed=1.0)
    heading = controller.team_heading(np.array([[5.0, 1.0]]), np.zeros((1, 2)), row)
    np.testing.assert_allclose(heading, [[5.0, 1.0] / np.hypot(5.0, 1.0)])  # waited 3: not yet past patience
    assert row[0, COLUMN["hit"]] == 0 and row[0, COLUMN["shortfall_x"]] == pytest.approx(0.8 + 0.1 * (1.0 - 0.8))
    heading = controller.team_heading(np.array([[5.0, 0.0]]), np.zeros((1, 2)), row)
    np.testing.assert_allclose(heading, [[0.5, -math.sqrt(3) / 2]], atol=1e-12)
    assert row[0, COLUMN["sigma"]] == -1 and degrees(row, "phi") == pytest.approx(60.0)
    assert row[0, COLUMN["hit"]] == 5.0 and (row[0, COLUMN["hit_x"]], row[0, COLUMN["hit_y"]]) == (-5.0, 0.0)
    assert row[0, COLUMN["shortfall_x"]] == pytest.approx(0.82)  # frozen from the begin: the wall's normal
    assert row[0, COLUMN["progress"]] == 1.0  # the bump sensor re-armed for the new heading
    assert row[0, COLUMN["closed"]] == 0  # both sides open


@pytest.mark.parametrize(("flips", "length"), [(0, 3.0), (1, 6.0), (2, 12.0)])
def test_leg_k_ends_d_2_to_the_k_along_the_wall_and_turns_back_on_the_other_side(flips: int, length: float) -> None:
    """D = 3 m: the centroid at (-5, y) from the goal is |y| along the wall from the hit point (-5, 0). Free, the
    heading first turns 0.85 deg back to the wall (phi 60 -> 59.15 deg); past D 2^k it turns back by pi."""
    controller = ShrinkingController(CH5)
    assert controller.settings.search_distance == 3.0
    for y, flipped in ((length - 0.01, False), (length + 0.01, True)):
        row = detour(controller, phi=60.0, peak=60.0, flips=flips, heading_y=0.0)
        controller.team_heading(np.array([[5.0, -y]]), np.zeros((1, 2)), row)
        assert row[0, COLUMN["flips"]] == flips + flipped
        assert row[0, COLUMN["sigma"]] == (-1 if flipped else 1)
        assert degrees(row, "phi") == pytest.approx(180.0 - 59.15 if flipped else 59.15)


def test_a_dead_end_turns_the_team_back_once() -> None:
    """E = 3 m behind the hit point (3.1 m back, 1 m along) while heading away from the wall: the team turns back;
    heading away from the wall no longer, it does not turn again; heading to the wall there, it never does."""
    controller = ShrinkingController(CH5)
    goal = np.array([[8.1, -1.0]])  # the centroid at (-8.1, 1): way (-3.1, 1) from the hit point
    row = detour(controller, phi=150.0, peak=150.0)  # -7.0 + 148 deg after the free turn back: away from the wall
    controller.team_heading(goal, np.zeros((1, 2)), row)
    assert row[0, COLUMN["flips"]] == 1 and row[0, COLUMN["sigma"]] == -1 and row[0, COLUMN["closed"]] == 1
    assert degrees(row, "phi") == pytest.approx(180.0 - 148.0)
    controller.team_heading(goal, np.zeros((1, 2)), row)
    assert row[0, COLUMN["flips"]] == 1
    row = detour(controller, phi=60.0, peak=60.0)
    controller.team_heading(goal, np.zeros((1, 2)), row)
    assert row[0, COLUMN["flips"]] == 0
    # turned past pi (200 - 2 = 198 deg): turned back by pi, phi = -18 deg, the team heads on the goal
    row = detour(controller, phi=200.0, peak=200.0)
    heading = controller.team_heading(goal, np.zeros((1, 2)), row)
    assert row[0, COLUMN["flips"]] == 1 and degrees(row, "phi") == pytest.approx(-18.0)
    np.testing.assert_allclose(heading, goal / np.linalg.norm(goal))


def test_after_a_dead_end_legs_end_only_at_the_next_one() -> None:
    """One side closed by a dead end: 7 m along the wall is past leg 1's 6 m, yet the team keeps on; open, it turns."""
    controller = ShrinkingController(CH5)
    for closed in (1.0, 0.0):
        row = detour(controller, phi=60.0, peak=60.0, flips=1, closed=closed)
        controller.team_heading(np.array([[5.0, 7.0]]), np.zeros((1, 2)), row)
        assert row[0, COLUMN["flips"]] == 2 - closed


def test_no_leg_ends_while_the_team_rounds_the_end_of_a_wall() -> None:
    """3.5 m along the wall (past D = 3): pressed last at phi = 170 deg and now free at 118 deg (120 - 2), it has
    turned back more than 40 deg round an end and keeps on; at 138 deg (less than 40 deg back) it turns back."""
    controller = ShrinkingController(CH5)
    for phi, flipped in ((120.0, False), (140.0, True)):
        row = detour(controller, phi=phi, peak=170.0)
        controller.team_heading(np.array([[5.0, -3.5]]), np.zeros((1, 2)), row)
        assert row[0, COLUMN["flips"]] == flipped


def test_a_first_leg_of_no_length_is_refused() -> None:
    with pytest.raises(ValueError, match="search_distance=0"):
        ShrinkingController(CH5, search_distance=0.0)


def test_the_old_detour_is_one_gain_away() -> None:
    """``wall_search=False``: the Bug2-like detour begins at the first blocked step and turns 1 deg per step."""
    controller = ShrinkingController(CH5, wall_search=False, patience=0)
    row = state(controller, heading_x=1.0, progress=0.2)
    controller.team_heading(np.array([[5.0, 0.0]]), np.zeros((1, 2)), row)
    assert row[0, COLUMN["hit"]] == 5.0 and degrees(row, "phi") == pytest.approx(1.0)


def test_every_agent_of_a_team_holds_the_same_search() -> None:
    """The search reads only c_g, its change and the shared memory: six agents with different lidars, offsets and
    indices but the same shared observations hold the same memory but their scale, step after step, in a corridor."""
    config = CH5.replace(scenes="corridor")
    env, controller = FormationEnv(config), ShrinkingController(config)
    rows, memory = np.stack(list(env.reset(seed=3)[0].values())), None
    columns = [column for name, column in COLUMN.items() if name != "scale"]
    began = False
    for _ in range(700):
        actions, memory = controller.predict(rows, memory)
        assert np.all(memory[:, columns] == memory[0, columns])
        began |= bool(memory[0, COLUMN["hit"]] > 0)
        rows, _, terminated, truncated, _ = env.step_array(actions)
        if terminated or truncated:
            break
    assert began  # the corridor's wall started a detour


class SlidingTeam:
    """A team sliding along the wall x = 0 (its centroid kept 0.5 m off it, the goal 20 m behind it), and along a
    wall y = ``corner`` across it if given: each step the centroid moves V dt along the heading, less what would take
    it closer than 0.5 m to a wall."""

    def __init__(self, controller: ShrinkingController, first_side: float, corner: float = math.inf) -> None:
        self.controller, self.position, self.corner = controller, np.array([-0.5, 0.0]), corner
        self.memory = state(controller, heading_x=1.0, lateral=0.1 * first_side)
        self.goal, self.moved = np.array([20.0, 0.0]), np.zeros(2)
        self.step_length = controller.settings.k_goal * CH5.v_max * CH5.dt

    def step(self) -> float:
        """One step; the centroid's travel along the wall x = 0 (m)."""
        heading = self.controller.team_heading((self.goal - self.position)[None, :], -self.moved[None, :], self.memory)[0]
        target = self.position + self.step_length * heading
        target = np.minimum(target, [-0.5, self.corner - 0.5])
        self.moved, self.position = target - self.position, target
        return abs(self.moved[1])


def test_a_corner_is_a_dead_end_that_closes_its_side() -> None:
    """A wall across the way 2 m past the hit point: the team turns at the corner, follows the new wall away from the
    goal and, E = 3 m behind the hit point, turns back once; that side closed, it then follows the wall the other way
    past leg 1's 6 m without turning."""
    controller = ShrinkingController(CH5)
    wall = SlidingTeam(controller, first_side=1.0, corner=2.0)
    while wall.memory[0, COLUMN["flips"]] == 0:
        seen = wall.position  # where the team is when it decides
        wall.step()
        assert seen[0] > -10.0
    assert -0.5 - 3.0 - wall.step_length <= seen[0] < -0.5 - 3.0 and seen[1] == 1.5
    assert wall.memory[0, COLUMN["closed"]] == 1
    while wall.position[1] > -7.0:
        wall.step()
        assert wall.memory[0, COLUMN["flips"]] == 1 and wall.position[1] < 1.5


@pytest.mark.parametrize(
    ("opening", "legs"),
    [(1.0, 0), (-1.0, 1), (3.1, 2), (-6.1, 3)],  # y of the opening: + on the first side; legs searched before it
)
def test_the_cow_path_bound_on_a_straight_wall(opening: float, legs: int) -> None:
    """The opening |y| = d away on a side: the legs before it go D 2^i out and back, so the travel along the wall up
    to it is 2 D (2^legs - 1) + d, each leg (and the last step) past its length by at most one step, and at most
    9 d + 2 D."""
    controller = ShrinkingController(CH5)
    wall, travel = SlidingTeam(controller, first_side=1.0), 0.0
    distance, side = abs(opening), math.copysign(1.0, opening)
    while wall.position[1] * side < distance:
        travel += wall.step()
        assert travel < 100.0
    assert wall.memory[0, COLUMN["flips"]] == legs
    d_flip, step = controller.settings.search_distance, wall.step_length
    exact = 2 * d_flip * (2**legs - 1) + distance
    assert exact <= travel <= exact + (2 * legs + 1) * step
    assert travel <= 9 * distance + 2 * d_flip + (2 * legs + 1) * step
