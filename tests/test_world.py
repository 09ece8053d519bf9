"""World: second-order dynamics (eq. 19, semi-implicit Euler), the speed clamp, and contacts with agents and walls."""

from __future__ import annotations

import gc
import math

import numpy as np
import pymunk
import pytest

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.formation_env import FormationEnv
from sb3_formation.env.scenarios import Scenario
from sb3_formation.env.world import World, clamp_speed

CONFIG = FormationConfig.task("ch4-individual")  # n = 3, R_a = 0.2 m, m = 1 kg, v_max = 0.05 m/s, dt = 0.3 s
V_MAX, DT, R_A = 0.05, 0.3, 0.2
F_MAX = 1.0 * 0.05 / 0.3  # m * v_max / dt = 1/6 N
STEP = V_MAX * DT  # 0.015 m: distance covered in one step at v_max
EXACT = 1e-12


def _world(
    positions: list[list[float]], obstacles: list[list[float]] | None = None, config: FormationConfig = CONFIG
) -> World:
    return World(config, Scenario(positions, [12.0, 8.0], obstacles if obstacles is not None else ()))


def _forces(*rows: tuple[float, float]) -> np.ndarray:
    return np.array(rows, dtype=np.float64)


FAR = [[2.0, 2.0], [2.0, 8.0]]  # two agents parked far from everything


def test_force_max_is_hand_value() -> None:
    """The config's F_max matches the hand value m * v_max / dt = 1/6 N used below."""
    assert CONFIG.force_max == pytest.approx(F_MAX, rel=1e-12)
    assert (CONFIG.agent_radius, CONFIG.v_max, CONFIG.dt, CONFIG.agent_mass) == (R_A, V_MAX, DT, 1.0)


def test_initial_state() -> None:
    """The world starts at the scenario's positions, at rest."""
    world = _world([[5.0, 5.0], *FAR])
    assert world.positions.shape == (3, 2) and world.velocities.shape == (3, 2)
    assert np.array_equal(world.positions, [[5.0, 5.0], [2.0, 2.0], [2.0, 8.0]])
    assert np.array_equal(world.velocities, np.zeros((3, 2)))


def test_unit_action_reaches_v_max_in_one_step() -> None:
    """From rest, F_max in +x gives v = F/m * dt = v_max, and the agent moves v_max * dt = 0.015 m (v first, then p)."""
    world = _world([[5.0, 5.0], *FAR])
    agent_contacts, obstacle_contacts = world.step(_forces((F_MAX, 0.0), (0.0, 0.0), (0.0, 0.0)))
    assert world.velocities[0] == pytest.approx([V_MAX, 0.0], abs=EXACT)
    assert math.hypot(*world.velocities[0]) == pytest.approx(V_MAX, abs=EXACT)
    assert world.positions[0] == pytest.approx([5.0 + 0.015, 5.0], abs=EXACT)  # not 5.0 (explicit Euler) nor 5.0075
    # the others received no force and stay put
    assert world.positions[1:] == pytest.approx(np.array(FAR), abs=EXACT)
    assert world.velocities[1:] == pytest.approx(np.zeros((2, 2)), abs=EXACT)
    assert agent_contacts == [0, 0, 0] and obstacle_contacts == [0, 0, 0]


def test_half_action_reaches_half_v_max() -> None:
    """F_max / 2 in -y gives v_max / 2 = 0.025 m/s and a move of 0.025 * 0.3 = 0.0075 m."""
    world = _world([[5.0, 5.0], *FAR])
    world.step(_forces((0.0, -0.5 * F_MAX), (0.0, 0.0), (0.0, 0.0)))
    assert world.velocities[0] == pytest.approx([0.0, -0.025], abs=EXACT)
    assert world.positions[0] == pytest.approx([5.0, 5.0 - 0.0075], abs=EXACT)


def test_mass_divides_force() -> None:
    """With m = 2 kg a force of 0.1 N for 0.3 s gives v = 0.1 / 2 * 0.3 = 0.015 m/s and a move of 0.0045 m."""
    config = CONFIG.replace(agent_mass=2.0)
    world = _world([[5.0, 5.0], *FAR], config=config)
    world.step(_forces((0.0, 0.1), (0.0, 0.0), (0.0, 0.0)))
    assert world.velocities[0] == pytest.approx([0.0, 0.015], abs=EXACT)
    assert world.positions[0] == pytest.approx([5.0, 5.0045], abs=EXACT)


def test_velocity_accumulates_then_coasts() -> None:
    """Quarter actions add up (v = 0.0125, 0.025 m/s), then with no force the agent keeps its speed (no damping)."""
    world = _world([[5.0, 5.0], *FAR])
    quarter = _forces((0.25 * F_MAX, 0.0), (0.0, 0.0), (0.0, 0.0))
    world.step(quarter)
    assert world.velocities[0, 0] == pytest.approx(0.0125, abs=EXACT)
    world.step(quarter)
    assert world.velocities[0, 0] == pytest.approx(0.025, abs=EXACT)
    # x = 5 + 0.0125 * 0.3 + 0.025 * 0.3 = 5.01125
    assert world.positions[0, 0] == pytest.approx(5.01125, abs=EXACT)
    world.step(np.zeros((3, 2)))
    assert world.velocities[0, 0] == pytest.approx(0.025, abs=EXACT)
    assert world.positions[0, 0] == pytest.approx(5.01125 + 0.0075, abs=EXACT)
    # an opposite full action from 0.025 m/s: 0.025 - 0.05 = -0.025 m/s
    world.step(_forces((-F_MAX, 0.0), (0.0, 0.0), (0.0, 0.0)))
    assert world.velocities[0, 0] == pytest.approx(-0.025, abs=EXACT)


def test_speed_clamped_diagonally() -> None:
    """Full forces on both axes, repeated: the speed stays v_max (not sqrt(2) v_max), along the diagonal."""
    world = _world([[5.0, 5.0], *FAR])
    start = world.positions[0].copy()
    diagonal = np.array([1.0, 1.0]) / math.sqrt(2.0)
    for step in range(1, 11):
        world.step(_forces((F_MAX, F_MAX), (0.0, 0.0), (0.0, 0.0)))
        assert math.hypot(*world.velocities[0]) == pytest.approx(V_MAX, abs=EXACT)
        assert world.velocities[0] == pytest.approx(V_MAX * diagonal, abs=EXACT)
        # each step covers v_max * dt along the diagonal
        assert world.positions[0] == pytest.approx(start + step * STEP * diagonal, abs=1e-10)


def test_speed_never_exceeds_v_max_under_random_forces() -> None:
    """Large random forces, obstacles and contacts: every speed stays <= v_max."""
    rng = np.random.default_rng(0)
    world = _world([[5.0, 5.0], [5.5, 5.0], [5.25, 5.5]], [[6.5, 5.0, 0.5]])
    for _ in range(60):
        world.step(rng.uniform(-5.0, 5.0, size=(3, 2)))
        assert np.all(np.hypot(*world.velocities.T) <= V_MAX + 1e-12)


# Contacts -----------------------------------------------------------------------------------------------------------


def test_agents_pushed_together_touch_once_per_pair() -> None:
    """Agents 0 and 1 start 0.1 m apart (surface gap) and are pushed towards each other at v_max.

    The gap closes by 2 * 0.015 = 0.03 m per step: 0.07, 0.04, 0.01 m after steps 1-3 (no contact); step 4 would
    make it -0.02 m, so they touch from step 4 on and count exactly one agent contact each per step.
    """
    world = _world([[5.0, 5.0], [5.5, 5.0], [2.0, 8.0]])
    push = _forces((F_MAX, 0.0), (-F_MAX, 0.0), (0.0, 0.0))
    for step in range(1, 21):
        agent_contacts, obstacle_contacts = world.step(push)
        distance = math.hypot(*(world.positions[1] - world.positions[0]))
        assert distance >= 2 * R_A - 0.01, (step, distance)
        assert obstacle_contacts == [0, 0, 0]
        if step <= 3:
            assert distance == pytest.approx(0.5 - 0.03 * step, abs=1e-10)
            assert agent_contacts == [0, 0, 0], step
        else:
            assert agent_contacts == [1, 1, 0], step


def test_middle_agent_counts_both_neighbours() -> None:
    """Agent 1 squeezed between agents 0 and 2 touches two agents: contacts [1, 2, 1] (each pair once)."""
    world = _world([[5.0, 5.0], [5.5, 5.0], [6.0, 5.0]])
    push = _forces((F_MAX, 0.0), (0.0, 0.0), (-F_MAX, 0.0))
    counts = []
    for _ in range(20):
        agent_contacts, _ = world.step(push)
        counts.append(agent_contacts)
        gaps = np.hypot(*np.diff(world.positions, axis=0).T)
        assert np.all(gaps >= 2 * R_A - 0.01), gaps
    # each outer agent closes a 0.1 m gap at 0.015 m per step: no contact in steps 1-6, contact from step 7 on
    assert counts[:6] == [[0, 0, 0]] * 6
    assert counts[10:] == [[1, 2, 1]] * 10


def test_agent_pushed_into_wall() -> None:
    """An agent 0.1 m from the right wall, pushed at v_max: touches in step 7 (6 * 0.015 = 0.09 < 0.1), stays inside."""
    world = _world([[14.7, 5.0], *FAR])
    push = _forces((F_MAX, 0.0), (0.0, 0.0), (0.0, 0.0))
    for step in range(1, 21):
        agent_contacts, obstacle_contacts = world.step(push)
        assert world.positions[0, 0] <= 15.0 - R_A + 0.01, (step, world.positions[0])
        assert world.positions[0, 1] == pytest.approx(5.0, abs=1e-9)
        assert agent_contacts == [0, 0, 0]
        assert obstacle_contacts == ([0, 0, 0] if step <= 6 else [1, 0, 0]), step


def test_agent_pushed_into_corner_touches_two_walls() -> None:
    """Pushed diagonally into the top-right corner, an agent touches both walls: 2 obstacle contacts.

    Per axis it moves 0.05 / sqrt(2) * 0.3 = 0.0106 m per step, so the 0.1 m gaps close in step 10.
    """
    world = _world([[14.7, 9.7], *FAR])
    push = _forces((F_MAX, F_MAX), (0.0, 0.0), (0.0, 0.0))
    counts = []
    for _ in range(20):
        counts.append(world.step(push)[1])
        assert world.positions[0, 0] <= 15.0 - R_A + 0.01 and world.positions[0, 1] <= 10.0 - R_A + 0.01
    assert counts[:9] == [[0, 0, 0]] * 9
    assert counts[9:] == [[2, 0, 0]] * 11


@pytest.mark.parametrize(("start", "force"), [((14.7, 5.0), (1.0, 0.0)), ((0.3, 5.0), (-1.0, 0.0)), ((7.0, 0.3), (0.0, -1.0))])
def test_every_wall_holds(start: tuple[float, float], force: tuple[float, float]) -> None:
    """The right, left and bottom walls all stop an agent pushed into them for 30 steps."""
    world = _world([list(start), [5.0, 5.0], [8.0, 5.0]])
    push = _forces((force[0] * F_MAX, force[1] * F_MAX), (0.0, 0.0), (0.0, 0.0))
    for _ in range(30):
        _, obstacle_contacts = world.step(push)
    x, y = world.positions[0]
    assert R_A - 0.01 <= x <= 15.0 - R_A + 0.01 and R_A - 0.01 <= y <= 10.0 - R_A + 0.01
    assert obstacle_contacts == [1, 0, 0]


def test_agent_pushed_into_obstacle() -> None:
    """An agent 0.1 m from a 1 m obstacle, pushed at it: touches in step 7, never sinks in more than 1 cm."""
    world = _world([[6.7, 5.0], *FAR], [[8.0, 5.0, 1.0]])
    push = _forces((F_MAX, 0.0), (0.0, 0.0), (0.0, 0.0))
    for step in range(1, 21):
        agent_contacts, obstacle_contacts = world.step(push)
        distance = math.hypot(*(world.positions[0] - [8.0, 5.0]))
        assert distance >= 1.0 + R_A - 0.01, (step, distance)
        assert agent_contacts == [0, 0, 0]
        assert obstacle_contacts == ([0, 0, 0] if step <= 6 else [1, 0, 0]), step


def test_agent_pushed_into_a_scene_wall_and_along_it() -> None:
    """A wall from (7, 2) to (7, 8), 0.2 m thick (face at x = 6.9); an agent at x = 6.6 (gap 0.1 m) pushed right:
    touches in step 7 as with the obstacle above, then stays outside (x <= 6.9 - 0.2 + 1 cm); one wall contact per
    step, counted with the obstacles. Pushed diagonally, it slides along the face (y keeps growing)."""
    world = World(CONFIG, Scenario([[6.6, 5.0], *FAR], [12.0, 8.0], walls=[[7.0, 2.0, 7.0, 8.0, 0.2]]))
    push = _forces((F_MAX, 0.0), (0.0, 0.0), (0.0, 0.0))
    for step in range(1, 21):
        _, obstacle_contacts = world.step(push)
        assert world.positions[0, 0] <= 6.9 - R_A + 0.01, (step, world.positions[0])
        assert obstacle_contacts == ([0, 0, 0] if step <= 6 else [1, 0, 0]), step
    slide = _forces((F_MAX / 2, F_MAX / 2), (0.0, 0.0), (0.0, 0.0))
    y = world.positions[0, 1]
    for _ in range(10):
        assert world.step(slide)[1] == [1, 0, 0]
        assert world.positions[0, 1] > y and world.positions[0, 0] <= 6.9 - R_A + 0.01
        y = world.positions[0, 1]


def test_contacts_stop_when_agents_part() -> None:
    """After touching, agents pulled apart report no more contacts."""
    world = _world([[5.0, 5.0], [5.41, 5.0], [2.0, 8.0]])
    world.step(_forces((F_MAX, 0.0), (-F_MAX, 0.0), (0.0, 0.0)))  # gap 0.01 m closes: contact
    assert world.step(_forces((F_MAX, 0.0), (-F_MAX, 0.0), (0.0, 0.0)))[0] == [1, 1, 0]
    apart = _forces((-F_MAX, 0.0), (F_MAX, 0.0), (0.0, 0.0))
    for _ in range(3):
        agent_contacts, _ = world.step(apart)
    assert agent_contacts == [0, 0, 0]


# clamp_speed ------------------------------------------------------------------------------------------------------


def test_clamp_speed_hand_values() -> None:
    """Faster velocities are scaled to v_max keeping their direction; slower ones are unchanged."""
    velocities = np.array([[3.0, 4.0], [0.3, 0.4], [0.0, 0.0], [-6.0, 8.0], [0.0, -2.0]])
    clamped = clamp_speed(velocities, 1.0)
    expected = np.array([[0.6, 0.8], [0.3, 0.4], [0.0, 0.0], [-0.6, 0.8], [0.0, -1.0]])  # |(3, 4)| = 5, |(-6, 8)| = 10
    assert clamped == pytest.approx(expected, abs=1e-15)
    assert velocities[0] == pytest.approx([3.0, 4.0])  # input untouched


def test_clamp_speed_at_limit_unchanged() -> None:
    """A speed exactly at v_max is left as it is; v_max = 5 scales (-6, 8) to (-3, 4)."""
    assert np.array_equal(clamp_speed(np.array([[3.0, 4.0]]), 5.0), [[3.0, 4.0]])
    assert clamp_speed(np.array([[-6.0, 8.0]]), 5.0) == pytest.approx(np.array([[-3.0, 4.0]]), abs=1e-15)
    assert clamp_speed(np.array([[0.05, 0.05]]), 0.05) == pytest.approx(np.array([[0.05, 0.05]]) / math.sqrt(2), abs=1e-15)


def test_resets_reuse_one_space_so_memory_stays_flat() -> None:
    """A Pymunk space is freed only by the cyclic garbage collector, so a new space per episode
    let thousands wait (memory grew by ~90 MiB). Every episode reuses the env's one space, holding only its own
    walls, obstacles and agents."""
    env = FormationEnv(FormationConfig.task("ch5-bearing", stage=3, max_steps=2))
    zero = {agent: np.zeros(2) for agent in env.possible_agents}
    gc.collect()
    gc.disable()  # nothing is collected: what the resets leave alive stays countable
    try:
        before = sum(isinstance(thing, pymunk.Space) for thing in gc.get_objects())
        for seed in range(200):
            env.reset(seed=seed)
            while env.agents:
                env.step(zero)
        after = sum(isinstance(thing, pymunk.Space) for thing in gc.get_objects())
    finally:
        gc.enable()
    assert after - before <= 1  # the env's own space (none before the first reset)
    space, obstacles = env.world.space, len(env.obstacles)
    assert len(space.shapes) == 4 + obstacles + 6 and len(space.bodies) == 4 + obstacles + 6  # walls, obstacles, agents
    env.reset(seed=7)
    assert env.world.space is space


def callback_contacts(world: World) -> set[tuple[tuple[str, int], tuple[str, int]]]:
    """The pairs (sorted ``(kind, index)``: kind ``"agent"`` or ``"obstacle"``) that Pymunk's ``pre_solve`` callback
    reports touching, filled as ``world`` steps (the caller empties it before each step)."""
    roles = {shape: ("agent", index) for index, body in enumerate(world.agent_bodies) for shape in body.shapes}
    roles |= {shape: ("obstacle", index) for index, body in enumerate(world._obstacle_bodies) for shape in body.shapes}
    pairs: set[tuple[tuple[str, int], tuple[str, int]]] = set()

    def record(arbiter: pymunk.Arbiter, space: pymunk.Space, data: object) -> None:
        first, second = sorted(roles[shape] for shape in arbiter.shapes)
        pairs.add((first, second))

    world.space.on_collision(None, None, pre_solve=record)
    return pairs


def test_contacts_match_pymunk_collision_callbacks() -> None:
    """The contact counts read from Pymunk's arbiters after each sub-step against an independent route: Pymunk's own
    ``pre_solve`` collision callbacks (called for every touching pair in every sub-step), on the same spaces, over
    crowded stage-3 episodes whose agents press on each other, the obstacles and the walls."""
    config = FormationConfig.task("ch5-bearing", stage=3, n_agents=8)
    rng = np.random.default_rng(5)
    touching = 0
    for seed in range(6):
        env = FormationEnv(config)
        env.reset(seed=seed)
        pairs = callback_contacts(env.world)
        for step in range(150):
            if step % 30 == 0:  # a new push every 30 steps: into the walls, obstacles and each other
                direction = rng.uniform(-1.0, 1.0, (config.n_agents, 2))
            pairs.clear()
            agents, obstacles = env.world.step(direction * config.force_max)
            expected_agents, expected_obstacles = [0] * config.n_agents, [0] * config.n_agents
            for (_, first), (kind, second) in pairs:
                if kind == "agent":  # two agents ("agent" < "obstacle")
                    expected_agents[first] += 1
                    expected_agents[second] += 1
                else:
                    expected_obstacles[first] += 1
            assert (agents, obstacles) == (expected_agents, expected_obstacles), (seed, step)
            touching += sum(agents) + sum(obstacles)
    assert touching > 500  # the episodes were crowded enough to test something


@pytest.mark.parametrize("n_agents", [3, 7, 16])
def test_positions_and_velocities_are_pymunks_own(n_agents: int) -> None:
    """The state read through Pymunk's batch API into the world's own array, against Pymunk's body attributes, over
    episodes of several sizes; Pymunk never moves that array (it would reallocate it if it ran out of room)."""
    config = FormationConfig.task("ch5-bearing", stage=3, n_agents=n_agents)
    env = FormationEnv(config)
    rng = np.random.default_rng(n_agents)
    for seed in range(3):
        env.reset(seed=seed)
        world = env.world
        for _ in range(40):
            world.step(rng.uniform(-1.0, 1.0, (n_agents, 2)) * config.force_max)
            assert world.positions.tolist() == [list(body.position) for body in world.agent_bodies]
            velocities = np.array([list(body.velocity) for body in world.agent_bodies])
            assert world.velocities.tolist() == clamp_speed(velocities, config.v_max).tolist()  # clamped as promised
            buffer = world._read_buffer._float_arr.arr
            assert int(pymunk.batch.ffi.cast("uintptr_t", buffer)) == world._body_states.ctypes.data
