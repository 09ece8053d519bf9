"""The scenes registry and the scene families: one registry, determinism, the solvability check, the documented
parameter ranges for n = 3 to 8, the API."""

from __future__ import annotations

import ast
import math
from pathlib import Path

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

import sb3_formation
from sb3_formation import FormationConfig, FormationEnv
from sb3_formation.env.clearance import (
    ClearanceMap,
    goal_field,
    path_distance,
    reachable,
    shortest_path,
    shrunk_footprint,
    start_footprint,
)
from sb3_formation.env.families import (
    MOVING_FAMILIES,
    PLACEMENT_ROOM,
    SCENE_FAMILIES,
    TRAFFIC_CROSSINGS,
    WALL_THICKNESS,
    is_solvable,
)
from sb3_formation.env.scenarios import PlacementError, Scenario, start_formation
from sb3_formation.env.scenes import BENCHMARK_SCENES, SCENES, check_scenes_fit, draw_scenario, scene_slots
from sb3_formation.env.shapes import shape_gaps, wall_lengths

FAMILIES = [*SCENE_FAMILIES, "mixed", *MOVING_FAMILIES, "mixed-moving"]


def config_of(scenes: str, n_agents: int = 6, **changes: float) -> FormationConfig:
    return FormationConfig.task("ch5-bearing", n_agents=n_agents, scenes=scenes, stage=3, **changes)


def test_sizes_by_hand() -> None:
    """n = 6 (R_a 0.2, eta_c 1.2, d_ref 1.5, scale 0.9): r_0 = 0.9 min(1.2, 1.5 / (2 sin 30)) = 1.08, footprint
    1.28 m (the 2.56 m hexagon); smallest: 0.2 / sin 30 + 0.2 = 0.6 m. n = 3: r_0 = 0.9 * 1.5 / (2 sin 60) = 0.779423,
    smallest 0.2 / sin 60 + 0.2 = 0.430940."""
    assert start_footprint(config_of("passage")) == pytest.approx(1.28)
    assert shrunk_footprint(config_of("passage")) == pytest.approx(0.6)
    assert start_footprint(config_of("passage", 3)) == pytest.approx(0.779423 + 0.2, abs=1e-6)
    assert shrunk_footprint(config_of("passage", 3)) == pytest.approx(0.430940, abs=1e-6)


@pytest.mark.parametrize("scenes", FAMILIES)
def test_the_same_seed_draws_the_same_scene(scenes: str) -> None:
    config = config_of(scenes)
    for seed in range(3):
        first, second = (draw_scenario(config, 3, np.random.default_rng(seed)) for _ in range(2))
        for name in ("agent_positions", "goal", "obstacles", "walls"):
            np.testing.assert_array_equal(getattr(first, name), getattr(second, name))
        for one, other in zip(first.movers, second.movers, strict=True):
            np.testing.assert_array_equal(one.waypoints, other.waypoints)
            assert (one.radius, one.speed, one.motion, one.reacts) == (other.radius, other.speed, other.motion, other.reacts)
    others = [draw_scenario(config, 3, np.random.default_rng(seed)).goal for seed in range(3)]
    assert len({tuple(goal) for goal in others}) == 3


def gaps_between_parallel_walls(first: np.ndarray, second: np.ndarray) -> float:
    """Surface gap (m) between two parallel walls: the distance between their lines minus the half thicknesses."""
    direction = (first[2:4] - first[:2]) / np.linalg.norm(first[2:4] - first[:2])
    offset = second[:2] - first[:2]
    return abs(offset[0] * direction[1] - offset[1] * direction[0]) - (first[4] + second[4]) / 2


@pytest.mark.parametrize("n_agents", range(3, 9))
def test_every_draw_keeps_the_documented_ranges_and_is_solvable(n_agents: int) -> None:
    """For n = 3 to 8, 15 draws of each family: the parameters measured back from the shapes lie in the documented
    ranges (D_0 and D_min of the team); the start formation is clear of every shape; every scene is solvable."""
    start, smallest = 2 * start_footprint(config_of("passage", n_agents)), 2 * shrunk_footprint(config_of("passage", n_agents))
    for scenes in SCENE_FAMILIES:
        config = config_of(scenes, n_agents)
        rng = np.random.default_rng(100 + n_agents)
        for _ in range(15):
            scene = draw_scenario(config, 3, rng)
            walls, circles = scene.walls, scene.obstacles
            scene.validate(config)
            gaps = shape_gaps(scene.agent_positions, circles, walls, config.world_width, config.world_height)
            assert np.all(gaps >= config.agent_radius)
            assert is_solvable(config, scene.centroid, scene.goal, circles, walls)
            np.testing.assert_allclose(scene.centroid, scene.agent_positions.mean(axis=0))
            if scenes == "passage":  # two collinear walls; the opening is between their facing ends' surfaces
                assert len(walls) == 2 and np.allclose(walls[:, 0], walls[0, 0]) and np.allclose(walls[:, 2], walls[0, 0])
                opening = walls[1, 1] - walls[0, 3] - WALL_THICKNESS
                assert 1.15 * smallest - 1e-9 <= opening <= 1.1 * start + 1e-9
                assert 0.4 * config.world_width <= walls[0, 0] <= 0.6 * config.world_width
            elif scenes == "corridor":  # barrier parts, then the two channel walls
                channel = walls[2:]
                width = gaps_between_parallel_walls(channel[0], channel[1])
                assert 1.15 * smallest - 1e-9 <= width <= 0.9 * start + 1e-9 < start
                assert 1.5 * start - 1e-9 <= wall_lengths(channel)[0] <= 2.5 * start + 1e-9
            elif scenes == "trap":  # the back wall, then the two arms towards the team
                inner = gaps_between_parallel_walls(walls[1], walls[2])
                assert 1.2 * start - 1e-9 <= inner <= 1.6 * start + 1e-9
                assert 0.8 * start - 1e-9 <= wall_lengths(walls[1:])[0] <= 1.2 * start + 1e-9
                # the U opens towards the team: its arms' free ends are nearer the start than the back wall
                back = walls[0, :2] / 2 + walls[0, 2:4] / 2
                mouth = walls[1, 2:4] / 2 + walls[2, 2:4] / 2
                assert np.linalg.norm(mouth - scene.centroid) < np.linalg.norm(back - scene.centroid)
            else:
                assert 8 <= len(circles) <= 12 and np.all((circles[:, 2] >= 0.3) & (circles[:, 2] <= 0.6))
                centres = circles[:, :2]
                between = (
                    np.hypot(*(centres[:, None] - centres[None]).transpose(2, 0, 1)) - circles[:, 2] - circles[:, 2, None]
                )
                assert between[np.triu_indices(len(circles), 1)].min() >= 1.1 * smallest - 1e-9


def cross(first: np.ndarray, second: np.ndarray) -> float:
    """The z component of the cross product of two plane vectors."""
    return float(first[0] * second[1] - first[1] * second[0])


@pytest.mark.parametrize("scenes", MOVING_FAMILIES)
def test_moving_families_keep_their_documented_traffic(scenes: str) -> None:
    """20 draws of each family with moving obstacles: its static part as the static family's (same walls and circles
    counts), and movers of the documented count, radius, speed (shares of v_max) and motion, each on a line that
    crosses the straight way between TRAFFIC_CROSSINGS of it, its start on that line, and the whole line clear of the
    starting formation, the static shapes and the border by PLACEMENT_ROOM plus its radius (checked at 1 cm)."""
    config = config_of(scenes)
    family = MOVING_FAMILIES[scenes]
    traffic = family.traffic
    assert traffic is not None
    rng = np.random.default_rng(5)
    footprint = start_footprint(config)
    for _ in range(20):
        scene = draw_scenario(config, 3, rng)
        scene.validate(config)
        movers = scene.movers
        assert traffic.count[0] <= len(movers) <= traffic.count[1]
        assert len(scene.walls) <= family.max_walls and len(scene.obstacles) <= family.max_circles
        start, goal = scene.centroid, scene.goal
        for mover in movers:
            assert mover.motion == traffic.motion and mover.reacts == traffic.reacts
            assert traffic.radius[0] <= mover.radius <= traffic.radius[1]
            assert traffic.speed[0] * config.v_max - 1e-12 <= mover.speed <= traffic.speed[1] * config.v_max + 1e-12
            middle, second, first = mover.waypoints
            along = second - first
            assert abs(cross(along, middle - first)) < 1e-9 * np.dot(along, along)  # the start on the line
            points = first + np.linspace(0, 1, int(np.linalg.norm(along) / 0.01) + 2)[:, None] * along
            gaps = shape_gaps(points, scene.obstacles, scene.walls, config.world_width, config.world_height)
            assert gaps.min() >= mover.radius + PLACEMENT_ROOM - 1e-6
            assert np.hypot(*(points - start).T).min() >= footprint + mover.radius + PLACEMENT_ROOM - 1e-6
            # where the line crosses the straight way, as a share of it
            way = goal - start
            share = cross(first - start, along) / cross(way, along)
            assert TRAFFIC_CROSSINGS[0] - 1e-9 <= share <= TRAFFIC_CROSSINGS[1] + 1e-9


def test_mixed_draws_every_family() -> None:
    """Over 40 episodes "mixed" meets scenes with walls of 2, 3 and 4 (passage, trap, corridor) and with circles."""
    config = config_of("mixed")
    rng = np.random.default_rng(0)
    kinds = {(len(scene.walls), len(scene.obstacles) > 0) for scene in (draw_scenario(config, 3, rng) for _ in range(40))}
    assert {(2, False), (3, False), (4, False), (0, True)} <= kinds


def test_an_unsolvable_scene_is_refused() -> None:
    """A passage whose opening (1.0 m) is narrower than the smallest hexagon (1.2 m) plus margins is refused; 1.4 m
    passes. The refusal comes from the map, not from the placement: the start and the goal are clear either way."""
    config = config_of("passage")

    def passage(opening: float) -> np.ndarray:
        low, high = 5.0 - opening / 2 - WALL_THICKNESS / 2, 5.0 + opening / 2 + WALL_THICKNESS / 2
        return np.array([[7.5, 0.0, 7.5, low, WALL_THICKNESS], [7.5, high, 7.5, 10.0, WALL_THICKNESS]])

    start, goal = np.array([3.0, 5.0]), np.array([12.0, 5.0])
    assert not is_solvable(config, start, goal, np.zeros((0, 3)), passage(1.0))
    assert is_solvable(config, start, goal, np.zeros((0, 3)), passage(1.4))


def test_a_family_that_cannot_fit_the_world_is_refused_with_a_message() -> None:
    """An 8 m x 5 m world leaves no room for a corridor of 1.5-2.5 formation widths and a team on each side."""
    with pytest.raises(ValueError, match=r"could not draw a solvable 'corridor' scene in the 8 m x 5 m world"):
        check_scenes_fit(config_of("corridor", world_width=8.0, world_height=5.0))
    with pytest.raises(PlacementError):
        draw_scenario(config_of("corridor", world_width=8.0, world_height=5.0), 3, np.random.default_rng(0))


def test_paths_through_a_small_maze() -> None:
    """A 6 m x 4 m maze: two walls from alternate sides force an S; a disc of radius 0.3 m finds the way (every point
    of the path clears the walls by 0.3 m, and the path is longer than the straight line), a disc of 1.2 m does not."""
    config = FormationConfig(world_width=6.0, world_height=4.0, n_agents=3, eta_c=0.5, d_ref=0.8)
    walls = np.array([[2.0, 0.0, 2.0, 2.8, 0.2], [4.0, 1.2, 4.0, 4.0, 0.2]])
    clearance = ClearanceMap.of(config, np.zeros((0, 3)), walls)
    start, goal = np.array([0.8, 1.0]), np.array([5.2, 3.0])
    path = shortest_path(clearance, start, goal, 0.3, 0.3)
    assert path is not None
    np.testing.assert_array_equal(path[0], start)
    assert np.linalg.norm(path[-1] - goal) <= 0.3 + 1e-9
    assert np.all(shape_gaps(path[1:], np.zeros((0, 3)), walls, 6.0, 4.0) >= 0.3)
    assert np.all(np.linalg.norm(np.diff(path[1:], axis=0), axis=1) <= 0.1 * math.sqrt(2) + 1e-9)  # neighbouring cells
    assert path[:, 1].max() > 2.8 + 0.1 + 0.3 - 0.05 and path[:, 1].min() < 1.2 - 0.1 - 0.3 + 0.05  # over, then under
    assert not reachable(clearance, start, goal, 0.3, 1.2)


@pytest.mark.parametrize("scenes", FAMILIES)
def test_the_pettingzoo_api_on_every_family(scenes: str) -> None:
    parallel_api_test(FormationEnv(config_of(scenes, max_steps=60)), num_cycles=100)


def test_a_hand_made_scene_with_walls_is_placed_as_given() -> None:
    config = config_of("passage")
    positions = start_formation(config, np.array([3.0, 5.0]))
    scene = Scenario(positions, [12.0, 5.0], walls=[[7.5, 0.0, 7.5, 4.0, 0.2]])
    env = FormationEnv(config)
    env.reset(options={"scenario": scene})
    np.testing.assert_array_equal(env.walls, scene.walls)
    with pytest.raises(ValueError, match="agent_0 overlaps wall 0"):
        env.reset(options={"scenario": Scenario(positions, [12.0, 5.0], walls=[[2.0, 3.9, 4.0, 3.9, 0.4]])})
    with pytest.raises(ValueError, match=r"wall 0's end at \(16.000, 5.000\) m is outside the world"):
        env.reset(options={"scenario": Scenario(positions, [12.0, 5.0], walls=[[9.0, 5.0, 16.0, 5.0, 0.2]])})
    with pytest.raises(ValueError, match=r"wall 0 has thickness 0\.0 m"):
        Scenario(positions, [12.0, 5.0], walls=[[9.0, 5.0, 10.0, 5.0, 0.0]])


def test_the_way_round_a_wall_by_hand() -> None:
    """A wall x = 7.5 from the floor to y = 6 (0.2 m thick) between a point and the goal (12, 3): the way is the straight
    line to the wall's upper corner (7.6, 6.1) and on to the goal; in the open it is the straight distance. The
    16-connected grid keeps both within 5 %, and a move towards the goal shortens the way by its length within 5 %."""
    config = FormationConfig.task("ch5-bearing")
    goal = np.array([12.0, 3.0])
    clearance = ClearanceMap.of(config, np.zeros((0, 3)), np.array([[7.5, 0.0, 7.5, 6.0, 0.2]]))
    field = goal_field(clearance, goal)
    corner = np.array([7.4, 6.1])  # the wall's end seen from the left: its left face, its top
    for point in ([3.0, 3.0], [5.0, 1.0], [6.0, 5.0]):
        point = np.array(point)
        by_hand = np.linalg.norm(corner - point) + np.linalg.norm(goal - np.array([7.6, 6.1])) + 0.2
        assert path_distance(clearance, field, point) == pytest.approx(by_hand, rel=0.05)
    for point in ([12.0, 8.0], [9.0, 3.0], [14.0, 1.0]):  # in sight of the goal
        point = np.array(point)
        assert path_distance(clearance, field, point) == pytest.approx(np.linalg.norm(goal - point), rel=0.05, abs=0.15)
    for point in ([9.5, 7.0], [13.0, 8.5], [10.0, 1.0]):  # 0.3 m straight towards the goal shortens the way as much
        point = np.array(point)
        move = 0.3 * (goal - point) / np.linalg.norm(goal - point)
        shortened = path_distance(clearance, field, point) - path_distance(clearance, field, point + move)
        assert shortened == pytest.approx(0.3, rel=0.05)


def test_the_way_from_inside_a_circle_is_finite() -> None:
    """A team can ring a circle, its centroid inside it: the way is then the straight distance to the nearest cells
    with a way (out of the circle) plus theirs, here the straight distance to the goal within 5 %."""
    config = FormationConfig.task("ch5-bearing")
    clearance = ClearanceMap.of(config, np.array([[5.0, 5.0, 0.5]]), np.zeros((0, 5)))
    field = goal_field(clearance, np.array([12.0, 5.0]))
    assert path_distance(clearance, field, np.array([5.0, 5.0])) == pytest.approx(7.0, rel=0.05)
    assert path_distance(clearance, field, np.array([5.3, 5.1])) == pytest.approx(np.hypot(6.7, 0.1), rel=0.05)


def test_the_geodesic_goal_term_rewards_going_round_the_wall() -> None:
    """A team behind the wall, its goal straight ahead beyond it, moves up along the wall towards its end: the straight
    distance grows (the thesis's goal term is below k_1), the way round shrinks (above k_1 with goal_progress:
    geodesic). The goal term is k_1 + (w_t - w_t+1) / (dt v_max) of the engine's ways."""
    walls = np.array([[7.5, 0.0, 7.5, 6.0, 0.2]])
    terms, observations = {}, {}
    for progress in ("euclidean", "geodesic"):
        config = FormationConfig.task("ch5-bearing", stage=3).replace(goal_progress=progress)
        scenario = Scenario(start_formation(config, np.array([5.0, 3.0])), [10.0, 3.0], walls=walls)
        env = FormationEnv(config)
        env.reset(seed=0, options={"scenario": scenario})
        engine = env.engine
        before = float(engine.latest.ways[0])
        up = np.tile([0.0, 1.0], (config.n_agents, 1))
        observations[progress], _, _, _, infos = env.step_array(up)
        after = float(engine.latest.ways[0])
        goal_term = infos[0]["reward_goal"]
        assert goal_term == pytest.approx(config.k1 + (before - after) / (config.dt * config.v_max), abs=1e-9)
        terms[progress] = goal_term
        if progress == "euclidean":  # the thesis's: the way is the goal distance itself
            assert after == float(engine.latest.goal_distances[0])
    assert terms["euclidean"] < FormationConfig.task("ch5-bearing").k1 < terms["geodesic"]
    # only the training reward reads the map: the observed previous reward (Table 3.1) is the thesis's in both
    np.testing.assert_array_equal(observations["euclidean"], observations["geodesic"])


def test_one_registry_places_every_episode() -> None:
    """Every way of placing an episode is an entry of ``SCENES``: the curriculum beside the families and their
    mixture; the benchmark plays every entry but the mixture; an unknown name is refused in one line."""
    moving = ["crowd", "crowd-blind", "passage-moving", "corridor-moving", "trap-moving", "clutter-moving"]
    crossing = ["crossing", "crossing-4"]
    assert list(SCENES) == [
        "curriculum",
        "passage",
        "corridor",
        "trap",
        "clutter",
        "mixed",
        *moving,
        "mixed-moving",
        *crossing,
    ]
    assert BENCHMARK_SCENES == ("curriculum", "passage", "corridor", "trap", "clutter", *moving, *crossing)
    assert [name for name, scenes in SCENES.items() if scenes.staged] == ["curriculum"]
    assert scene_slots(config_of("mixed")) == (12, 4)  # clutter's 12 circles, the corridor's 4 walls
    assert scene_slots(config_of("curriculum")) == (4, 0)  # stages 1-2: three large obstacles and a small one
    with pytest.raises(ValueError, match=r"^FormationConfig.scenes='maze' is invalid: it must be one of \('curriculum'"):
        check_scenes_fit(config_of("maze"))
    with pytest.raises(ValueError, match="scenes='maze'"):
        FormationEnv(config_of("maze"))


def scene_name_tests(path: Path) -> list[str]:
    """The comparisons in a source file that test a value against a name of ``SCENES`` (``x == "passage"``,
    ``x in ("curriculum", ...)``, ``match``/``case "trap"``), read from its syntax tree."""
    names, found = set(SCENES), []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Compare):
            operands = [node.left, *node.comparators]
            constants = [
                item
                for operand in operands
                for item in (operand.elts if isinstance(operand, ast.Tuple | ast.List | ast.Set) else [operand])
            ]
            if any(isinstance(item, ast.Constant) and item.value in names for item in constants):
                found.append(f"{path.name}:{node.lineno}")
        elif isinstance(node, ast.MatchValue) and isinstance(node.value, ast.Constant) and node.value.value in names:
            found.append(f"{path.name}:{node.lineno}")
    return found


def test_no_scene_name_is_tested_outside_the_registry() -> None:
    """No module of the package branches on a scene's name: what differs between scenes is an attribute or a method
    of their entry in ``SCENES``. (Checked by an independent route: the syntax tree of every source file.)"""
    package = Path(sb3_formation.__file__).parent
    registry = {package / "env" / name for name in ("scenes.py", "families.py", "curriculum.py")}
    found = [test for path in sorted(package.rglob("*.py")) if path not in registry for test in scene_name_tests(path)]
    assert found == []
    assert scene_name_tests(Path(__file__)) != []  # the check finds the comparisons of this very file


def test_the_check_finds_a_branch_on_a_scene_name(tmp_path: Path) -> None:
    source = tmp_path / "branchy.py"
    source.write_text('def suffix(scenes):\n    return "" if scenes == "curriculum" else scenes\n')
    assert scene_name_tests(source) == ["branchy.py:2"]
