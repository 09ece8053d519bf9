"""The safety filter: its QP against hand-solved cases and a library solver, decentralisation, and no contacts."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sb3_formation.controllers import CONTROLLERS
from sb3_formation.controllers.base import PrivilegedPolicy
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.formation_env import FormationEnv
from sb3_formation.env.observations import observation_fields, observation_layout
from sb3_formation.env.sensors import ray_directions
from sb3_formation.safety import SafetyFilter, SafetyGains
from sb3_formation.safety.policy import SafePolicy
from sb3_formation.safety.qp import solve_one, solve_with_library
from sb3_formation.sb3.safety import SafetyVecEnv
from sb3_formation.sb3.vec_env import FormationVecEnv

CONFIG = FormationConfig.task("ch5-bearing", stage=3)
LAYOUT = observation_layout(observation_fields(CONFIG))
GAINS = SafetyGains()
STEP = CONFIG.v_max * CONFIG.dt  # m: a step's travel at v_max (the unit of the barriers' right-hand sides)
RHO = GAINS.slack_weight


def free_row(preceding: tuple[float, float] = (-0.8, 0.8), succeeding: tuple[float, float] = (-0.8, -0.8)) -> np.ndarray:
    """A raw observation row at rest with nothing in lidar range and its neighbours at the given offsets (m)."""
    row = np.zeros(sum(field.size for field in observation_fields(CONFIG)))
    row[LAYOUT["lidar_obstacles"]] = 1.0
    row[LAYOUT["lidar_agents"]] = 1.0
    row[LAYOUT["neighbour_offsets"]] = [*preceding, *succeeding]
    return row


def projected(target: float, bound: float) -> float:
    """The solution u of ``min (u - target)^2 + rho s^2`` with ``u - s <= bound`` (bound < target), by hand:
    u = bound + s and the derivative 2 (bound + s - target) + 2 rho s = 0 give s = (target - bound) / (1 + rho)."""
    return bound + (target - bound) / (1.0 + RHO)


def test_an_action_into_a_wall_is_projected_onto_the_barriers_half_plane() -> None:
    row = free_row()
    gap = 0.02  # m from the agent's surface, seen by the ray along +x only
    row[LAYOUT["lidar_obstacles"].start] = gap / CONFIG.lidar_range
    action = np.array([[0.6, 0.3]], dtype=np.float32)  # from rest: commands 0.6 v_max, 0.3 v_max (within v_max)
    safe, report = SafetyFilter(CONFIG).filter(row[None], action)
    bound = GAINS.gamma * (gap - GAINS.obstacle_margin) / STEP  # x-speed (units of v_max) that keeps h' >= (1 - gamma) h
    assert bound == pytest.approx(1.0 / 3.0)
    # from rest a unit action commands v_max: the action is the commanded velocity in units of v_max
    np.testing.assert_allclose(safe[0], [projected(0.6, bound), 0.3], rtol=0, atol=1e-6)
    assert report.changed.tolist() == [True] and report.infeasible.tolist() == [False]
    assert report.change[0] == pytest.approx(0.6 - projected(0.6, bound), abs=1e-6)
    assert report.separation[0] == pytest.approx(gap)


def test_two_agents_heading_at_each_other_each_take_half() -> None:
    distance = 0.43  # m between centres: a gap of 3 cm
    first = free_row(preceding=(0.0, 1.2), succeeding=(distance, 0.0))
    second = free_row(preceding=(-distance, 0.0), succeeding=(0.0, -1.2))
    actions = np.array([[1.0, 0.0], [-1.0, 0.0]], dtype=np.float32)
    safe, report = SafetyFilter(CONFIG).filter(np.stack([first, second]), actions)
    barrier = distance - 2 * CONFIG.agent_radius - GAINS.agent_margin
    half = 0.5 * GAINS.gamma * barrier / STEP  # each agent's share of gamma h, in units of v_max
    np.testing.assert_allclose(safe, [[projected(1.0, half), 0.0], [-projected(1.0, half), 0.0]], rtol=0, atol=1e-6)
    closing = (safe[0, 0] - safe[1, 0]) * STEP  # m: the gap lost in the step
    assert closing == pytest.approx(GAINS.gamma * barrier, rel=1e-3)
    assert report.changed.all()


def test_a_neighbour_about_to_leave_the_communication_range_pulls_the_action_back() -> None:
    distance = 2.85  # m: 5 cm inside d_comm - comm_margin
    row = free_row(preceding=(distance, 0.0), succeeding=(0.0, -0.8))
    action = np.array([[-1.0, 0.0]], dtype=np.float32)  # away from it at full speed
    safe, _ = SafetyFilter(CONFIG).filter(row[None], action)
    reach = STEP / math.cos(math.pi / GAINS.speed_sides)  # the longest move: the speed polygon's apothem
    curvature = (2 * reach) ** 2 / (2 * distance)
    bound = 0.5 * (GAINS.gamma * (CONFIG.d_comm - GAINS.comm_margin - distance) - curvature) / STEP
    assert 0 < bound < 1
    np.testing.assert_allclose(safe[0], [-projected(1.0, bound), 0.0], rtol=0, atol=1e-6)


def test_actions_that_keep_every_constraint_come_back_bit_for_bit() -> None:
    rng = np.random.default_rng(0)
    rows = np.stack([free_row() for _ in range(5)])
    rows[:, LAYOUT["lidar_obstacles"]] = rng.uniform(0.5, 1.0, (5, CONFIG.lidar_rays))  # 0.75 m away and further
    actions = rng.uniform(-1, 1, (5, 2)).astype(np.float32)
    safe, report = SafetyFilter(CONFIG).filter(rows, actions)
    assert safe.dtype == np.float32 and np.array_equal(safe, actions)
    assert not report.changed.any() and not report.change.any()


def test_bad_actions_are_refused_with_one_line() -> None:
    safety = SafetyFilter(CONFIG)
    with pytest.raises(ValueError, match="not finite"):
        safety.filter(free_row()[None], np.array([[np.nan, 0.0]]))
    with pytest.raises(ValueError, match=r"\(1, 2\) actions"):
        safety.filter(free_row()[None], np.zeros((1, 3)))
    with pytest.raises(ValueError, match="observation rows"):
        safety.filter(np.zeros((1, 5)), np.zeros((1, 2)))
    with pytest.raises(ValueError, match=r"SafetyGains\.gamma"):
        SafetyGains(gamma=0.0)
    with pytest.raises(ValueError, match="unknown safety filter setting"):
        SafetyGains.from_dict({"gama": 0.5})


def fuzzed_problem(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A random problem of the filter's form: a target, safety rows (g, -1), a box and a polygon of hard rows (a, 0),
    and s >= 0; a share of them infeasible without slack."""
    target = rng.uniform(-1.5, 1.5, 2)
    centre = rng.uniform(-0.5, 0.5, 2)
    rows, rhs = [], []
    for axis in range(2):  # a box round a centre
        for sign in (1.0, -1.0):
            normal = np.zeros(2)
            normal[axis] = sign
            rows.append([*normal, 0.0])
            rhs.append(sign * centre[axis] + rng.uniform(0.3, 1.0))
    sides = int(rng.choice([0, 4, 6, 8, 16]))
    for angle in (np.arange(sides) + 0.5) * 2 * np.pi / max(sides, 1):
        rows.append([np.cos(angle), np.sin(angle), 0.0])
        rhs.append(1.0 / np.cos(np.pi / sides))
    for _ in range(int(rng.integers(1, 9))):
        direction = rng.normal(size=2)
        rows.append([*(direction / np.linalg.norm(direction)), -1.0])
        rhs.append(rng.uniform(-0.8, 1.0))
    rows.append([0.0, 0.0, -1.0])
    rhs.append(0.0)
    return target, np.array(rows), np.array(rhs)


def test_the_compiled_solver_equals_a_library_solver_on_fuzzed_problems() -> None:
    rng = np.random.default_rng(1)
    worst, slack_used = 0.0, 0
    for _ in range(10_000):
        target, rows, rhs = fuzzed_problem(rng)
        ours = solve_one(target, RHO, rows, rhs, len(rows))
        theirs = solve_with_library(target, RHO, rows, rhs, "daqp")
        worst = max(worst, float(np.abs(ours - theirs).max()))
        slack_used += ours[2] > GAINS.infeasible_slack
    assert worst < 1e-6
    assert 100 < slack_used < 9_000  # both kinds of problem were met


def test_the_filter_with_a_library_solver_equals_the_compiled_one() -> None:
    env = FormationEnv(CONFIG.replace(scenes="clutter"))
    rows = np.stack(list(env.reset(seed=3)[0].values()))
    actions = np.tile([[1.0, 0.0]], (len(rows), 1)).astype(np.float32)
    rows[:, LAYOUT["lidar_obstacles"]] = np.minimum(rows[:, LAYOUT["lidar_obstacles"]], 0.02)  # walls all round
    fast, _ = SafetyFilter(CONFIG).filter(rows, actions)
    library, _ = SafetyFilter(CONFIG, SafetyGains(solver="quadprog")).filter(rows, actions)
    np.testing.assert_allclose(fast, library, rtol=0, atol=1e-6)
    assert not np.array_equal(fast, actions)


def test_each_agents_filtered_action_depends_on_its_own_row_only() -> None:
    env = FormationEnv(CONFIG.replace(scenes="trap"))
    rows = np.stack(list(env.reset(seed=5)[0].values()))
    rows[:, LAYOUT["lidar_obstacles"]] *= 0.02  # everything close: most agents' filters act
    rng = np.random.default_rng(2)
    actions = rng.uniform(-1, 1, (len(rows), 2)).astype(np.float32)
    safety = SafetyFilter(CONFIG)
    together, report = safety.filter(rows, actions)
    assert report.changed.sum() >= len(rows) // 2
    for agent in range(len(rows)):
        others = rng.uniform(0, 1, rows.shape)
        others[agent] = rows[agent]
        other_actions = rng.uniform(-1, 1, actions.shape).astype(np.float32)
        other_actions[agent] = actions[agent]
        alone, _ = safety.filter(others, other_actions)
        assert np.array_equal(alone[agent], together[agent])


def adversarial_actions(rows: np.ndarray, config: FormationConfig, rng: np.random.Generator, kind: str) -> np.ndarray:
    """Every agent drives at the nearest thing it sees (a lidar return of either channel or a neighbour), or at random."""
    if kind == "random":
        return rng.uniform(-1, 1, (len(rows), 2))
    layout = observation_layout(observation_fields(config))
    directions = ray_directions(config.lidar_rays)
    actions = np.empty((len(rows), 2))
    for agent, row in enumerate(rows):
        readings = np.minimum(row[layout["lidar_obstacles"]], row[layout["lidar_agents"]]) * config.lidar_range
        offsets = row[layout["neighbour_offsets"]].reshape(2, 2)
        gaps = np.linalg.norm(offsets, axis=1) - 2 * config.agent_radius
        if readings.min() < gaps.min():
            direction = directions[int(readings.argmin())]
        else:
            direction = offsets[int(gaps.argmin())] / np.linalg.norm(offsets[int(gaps.argmin())])
        actions[agent] = direction + rng.normal(0, 0.2, 2)
    return np.clip(actions, -1, 1)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    scenes=st.sampled_from(["curriculum", "passage", "corridor", "trap", "clutter"]),
    n_agents=st.integers(3, 8),
    seed=st.integers(0, 10_000),
    kind=st.sampled_from(["random", "nearest"]),
)
def test_no_contacts_with_the_filter_on_except_on_reported_infeasible_steps(
    scenes: str, n_agents: int, seed: int, kind: str
) -> None:
    config = CONFIG.replace(scenes=scenes, n_agents=n_agents)
    env = FormationEnv(config)
    safety = SafetyFilter(config)
    rng = np.random.default_rng(seed)
    rows = np.stack(list(env.reset(seed=seed)[0].values()))
    infeasible_steps = 0
    for _ in range(400):
        safe, report = safety.filter(rows, adversarial_actions(rows, config, rng, kind))
        rows, _, terminated, truncated, infos = env.step_array(safe)
        contacts = sum(info["collisions_agent"] + info["collisions_obstacle"] for info in infos)
        infeasible_steps += bool(report.infeasible.any())
        if contacts:
            assert report.infeasible.any(), (
                f"a contact on a step the filter did not report infeasible ({scenes}, n={n_agents})"
            )
        if terminated or truncated:
            break
    assert infeasible_steps <= 20  # rare


def test_a_safe_policy_keeps_what_its_policy_is_and_reports_per_episode() -> None:
    planner = CONTROLLERS["privileged-planner"](CONFIG)
    safe = SafePolicy(SafePolicy(planner))
    assert safe.policy is planner  # one filter, not two
    assert isinstance(safe, PrivilegedPolicy) and not isinstance(
        SafePolicy(CONTROLLERS["classical"](CONFIG)), PrivilegedPolicy
    )
    env = FormationEnv(CONFIG.replace(scenes="clutter"))
    rows = np.stack(list(env.reset(seed=0)[0].values()))
    safe.start_episodes([0], [env.team_state()])
    starts = np.ones(len(rows), dtype=bool)
    for _ in range(3):
        safe.predict(rows, None, starts)
        starts[:] = False
    metrics = safe.episode_metrics(slice(0, len(rows)))
    assert safe.tally.steps.tolist() == [3] * len(rows)
    assert set(metrics) == {"filter_changed_fraction", "filter_change_mean", "filter_infeasible_steps", "min_separation"}
    assert 0 <= metrics["filter_changed_fraction"] <= 1


def test_shielded_vec_env_applies_the_filtered_action_penalises_the_change_and_reports_episodes() -> None:
    """The env steps with the filter's actions (an unwrapped twin stepped with the same safe actions returns the same
    observations), each reward loses ``penalty |a_safe - a|``, and an ended episode's info carries what the filter did
    (counted here independently from the filter's reports)."""
    config = CONFIG.replace(max_steps=12, formation_scale=0.36)  # neighbours 3 cm apart
    shielded = SafetyVecEnv(FormationVecEnv(config, n_envs=2), penalty=2.0)
    twin = FormationVecEnv(config, n_envs=2)
    shielded.seed(4)
    twin.seed(4)
    rows, twin_rows = shielded.reset(), twin.reset()
    safety, rng = SafetyFilter(config), np.random.default_rng(0)
    changed, steps = np.zeros(len(rows)), 0
    for _ in range(12):
        actions = adversarial_actions(rows, config, rng, "nearest")
        safe, report = safety.filter(rows, actions)
        changed += report.changed
        steps += 1
        rows, rewards, _, infos = shielded.step(actions)
        twin_rows, twin_rewards, _, _ = twin.step(safe)
        np.testing.assert_array_equal(rows, twin_rows)
        np.testing.assert_allclose(rewards, twin_rewards - 2.0 * report.change, rtol=0, atol=1e-5)
    assert changed.sum() > 0
    for team in range(2):  # max_steps 12: both teams' episodes ended at the last step
        episode = infos[team * config.n_agents]["formation_episode"]
        team_rows = slice(team * config.n_agents, (team + 1) * config.n_agents)
        assert episode["filter_changed_fraction"] == pytest.approx(changed[team_rows].sum() / (steps * config.n_agents))
        assert episode["filter_infeasible_steps"] == 0 and episode["min_separation"] > 0


@pytest.mark.filterwarnings("ignore:overflow encountered")
@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("velocity", np.nan),
        ("velocity", np.inf),
        ("lidar_obstacles", -np.inf),
        ("lidar_obstacles", np.nan),
        ("neighbour_offsets", np.nan),
    ],
)
def test_the_filter_never_returns_or_passes_a_non_finite_action(field: str, value: float) -> None:
    """A NaN or infinite velocity, lidar reading or neighbour offset in one row is refused in one line (it used to give
    NaN actions, or pass the proposed action through unreported); rows far beyond any reachable state (1e300 m) give
    finite actions or a one-line refusal, never NaN."""
    config = FormationConfig.task("ch5-bearing", stage=3)
    safety = SafetyFilter(config)
    env = FormationEnv(config)
    rows = np.stack(list(env.reset(seed=0)[0].values())).astype(np.float64)
    layout = env.observation_layout
    spoilt = rows.copy()
    spoilt[2, layout[field].start] = value
    with pytest.raises(ValueError, match="observation rows that are not finite") as error:
        safety.filter(spoilt, np.zeros((6, 2)))
    assert "\n" not in str(error.value)
    huge = rows.copy()
    huge[:, layout["neighbour_offsets"]] = 1e300
    huge[:, layout["velocity"]] = 1e300
    try:
        safe, _ = safety.filter(huge, np.ones((6, 2)))
    except ValueError as refused:
        assert "\n" not in str(refused)
    else:
        assert np.isfinite(safe).all()
