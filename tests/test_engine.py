"""The stepping engine reproduces the golden trajectories recorded before it was written (``tests/engine_goldens.py``):
every task, team sizes 3 to 16 in one VecEnv, 1 to 3 processes, terminal observations, stage changes, the PettingZoo
env's resets and state, and evaluations, bit for bit."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from engine_goldens import EARLY_STEPS, GOLDENS, TASKS, case_name, cases, early_steps

from sb3_formation import FormationConfig, FormationEnv
from sb3_formation.env.config import INFO_KEYS, REWARD_TERMS
from sb3_formation.env.dynamics import HolonomicDynamics, UnicycleDynamics
from sb3_formation.env.engine import INFO_VALUES, ContactColumn, FormationEngine, InfoColumn, agent_infos
from sb3_formation.env.progress import EuclideanProgress, GeodesicProgress
from sb3_formation.env.scenarios import Scenario
from sb3_formation.env.slots import slot_observations
from sb3_formation.experiment.pretrained import numerics_fingerprint
from sb3_formation.sb3.vec_env import FormationVecEnv

SIZES = list(range(3, 17))

CASES = dict(cases())


def golden(name: str) -> list[str]:
    data = json.loads(GOLDENS.read_text())
    recorded = data["by_numerics"].get(numerics_fingerprint())
    if recorded is None:  # pragma: no cover - another CPU
        pytest.skip(
            f"no goldens for this CPU's float kernels; record them from {data['recorded_from'][:7]} (see "
            "tests/engine_goldens.py)"
        )
    return recorded[case_name(name)]


@pytest.mark.parametrize("name", list(CASES))
def test_the_engine_reproduces_the_golden_trajectories(name: str) -> None:
    expected = golden(name)
    played = CASES[name]()
    first = next((step for step, (a, b) in enumerate(zip(played, expected)) if a != b), None)
    assert first is None and len(played) == len(expected), f"{name}: first different digest at step {first}"


@pytest.mark.parametrize("task", TASKS)
def test_the_first_steps_agree_with_the_recorded_values_on_any_cpu(task: str) -> None:
    """Where no digest of this CPU is recorded, this still checks the engine's numbers: 200 steps of a team of 6, within
    1e-9 of the values recorded on a CPU whose digests pass (bit for bit there)."""
    with np.load(EARLY_STEPS) as recorded:
        expected = recorded[task]
    played = early_steps(task)
    assert played.shape == expected.shape == (200, 36) and np.ptp(expected[:, :12], axis=0).min() > 0.01  # they move
    np.testing.assert_allclose(played, expected, rtol=0, atol=1e-9)


def wide_actions(rng: np.random.Generator, slots: int) -> np.ndarray:
    """Random actions, a third of them beyond [-1, 1], so that agents collide and clipping is exercised."""
    return rng.normal(0.0, 1.5, (slots, 2))


def reference_vec_step(envs: list[FormationEnv], actions: np.ndarray) -> tuple:
    """A slot-per-agent VecEnv step done team by team, each team an engine of its own (``FormationEnv.step_array``)."""
    observations, rewards, dones, infos, start = [], [], [], [], 0
    for env in envs:
        n_agents = env.config.n_agents
        team_observations, team_rewards, terminated, truncated, team_infos = env.step_array(
            np.clip(actions[start : start + n_agents], -1.0, 1.0)
        )
        start += n_agents
        if terminated or truncated:
            for info, terminal in zip(team_infos, team_observations):
                info["terminal_observation"] = terminal
                info["TimeLimit.truncated"] = truncated and not terminated
            summary = env.episode_summary()
            team_infos[0].update(episode={"r": summary["return"], "l": summary["length"]}, formation_episode=summary)
            team_infos[0]["is_success"] = terminated
            team_observations = np.stack(list(env.reset()[0].values()))
        observations.append(team_observations)
        rewards.append(team_rewards)
        dones.append(np.full(n_agents, terminated or truncated))
        infos += team_infos
    return np.concatenate(observations), np.concatenate(rewards).astype(np.float32), np.concatenate(dones), infos


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_a_team_steps_in_a_vec_env_as_it_steps_alone(workers: int) -> None:
    """Teams of sizes 3 to 16 in one ``FormationVecEnv`` (in this process, or split between it and 1 or 2 worker
    processes) against the same teams stepped one by one, each an engine of its own: observations, rewards, dones and
    infos (terminal observations and team-episode records) agree, also after the curriculum changes the stage of some
    teams. A team's numbers never depend on the other teams of its engine."""
    config = FormationConfig.task("ch5-bearing", stage=3, max_steps=25)
    venv = FormationVecEnv(config, n_envs=len(SIZES), n_workers=workers, team_sizes=SIZES, start_method="fork")
    venv.seed(3)
    observations = venv.reset()
    envs = [FormationEnv(config.replace(n_agents=n)) for n in SIZES]
    starts = np.concatenate([[0], np.cumsum(SIZES)])
    expected = np.concatenate([np.stack(list(env.reset(seed=3 + int(start))[0].values())) for env, start in zip(envs, starts)])
    assert np.array_equal(observations, expected)
    rng = np.random.default_rng(1)
    ends = 0
    for step in range(70):
        if step == 30:  # as the curriculum callback does it: the new stage's rewards at once
            venv.env_method("set_stage", 2, indices=[0, int(starts[5])])
            for team in (0, 5):
                envs[team].set_stage(2)
        actions = wide_actions(rng, venv.num_envs)
        observations, rewards, dones, infos = venv.step(actions)
        reference = reference_vec_step(envs, actions)
        assert np.array_equal(observations, reference[0]) and np.array_equal(rewards, reference[1])
        assert np.array_equal(dones, reference[2])
        for info, expected_info in zip(infos, reference[3]):
            if "episode" in info:
                ends += 1
                assert info.pop("episode").keys() == {"r", "l", "t"} and info["formation_episode"]["stage"] in (2, 3)
                expected_info.pop("episode")
            terminal, expected_terminal = (
                info.pop("terminal_observation", None),
                expected_info.pop("terminal_observation", None),
            )
            assert (terminal is None) == (expected_terminal is None)
            assert terminal is None or np.array_equal(terminal, expected_terminal)
            assert info == expected_info
    assert ends >= 2 * len(SIZES)
    assert venv.get_attr("stage", indices=[0, int(starts[1]), int(starts[5])]) == [2, 3, 2]
    venv.close()


def test_team_observations_are_built_from_the_batch() -> None:
    """With a team critic each slot sees its team's rows after its own, as ``slot_observations`` builds them."""
    config = FormationConfig.task("ch4-team", stage=3, max_steps=10)
    venv = FormationVecEnv(config, n_envs=2, team_observations=True)
    venv.seed(0)
    venv.reset()
    env = FormationEnv(config)
    env.reset(seed=0)
    for _ in range(12):
        observations, _, _, _ = venv.step(np.full((6, 2), 0.3))
        own = np.stack(list(env.step(dict.fromkeys(env.possible_agents, np.full(2, 0.3)))[0].values()))
        if not env.agents:
            own = np.stack(list(env.reset()[0].values()))
        assert np.array_equal(observations[:3], slot_observations(own, 3, True))


def test_teams_not_in_an_episode_are_not_stepped() -> None:
    """An engine steps only its live teams: a team that ended (or was never reset) keeps its rows as they were, and an
    engine with no live team steps nothing."""
    engine = FormationEngine([FormationConfig.task("ch4-individual", stage=3, max_steps=2)] * 3)
    engine.reset(0, seed=0)
    engine.reset(2, seed=2)
    alone = FormationEnv(FormationConfig.task("ch4-individual", stage=3, max_steps=2))
    alone.reset(seed=2)
    actions = np.full((9, 2), 0.5)
    first = engine.step(actions)
    assert not first.observations[3:6].any() and not first.rewards[3:6].any()  # team 1 was never reset
    assert np.array_equal(first.observations[6:], alone.step_array(actions[6:])[0])
    engine.reset(1, seed=1)
    second = engine.step(actions)  # ends teams 0 and 2 (T_s = 2); team 1 plays its first step
    assert second.truncated.tolist() == [True, False, True] and engine.live.tolist() == [False, True, False]
    third = engine.step(actions)
    assert np.array_equal(third.observations[:3], second.observations[:3])  # team 0 ended: its terminal observations
    assert np.array_equal(third.positions[6:], second.positions[6:]) and third.truncated.tolist() == [False, True, False]
    nothing = engine.step(actions)
    assert np.array_equal(nothing.observations, third.observations) and not nothing.rewards.any()


def test_returned_arrays_never_change_afterwards() -> None:
    """A reset copies an array the engine has returned before it writes the reset team's rows."""
    engine = FormationEngine([FormationConfig.task("ch5-bearing", max_steps=1)] * 2)
    engine.reset(0, seed=0)
    engine.reset(1, seed=1)
    step = engine.step(np.zeros((12, 2)))
    kept = [np.copy(array) for array in step]
    engine.reset(0, seed=5)
    assert all(np.array_equal(array, copy) for array, copy in zip(step, kept))


def test_a_finished_team_is_refused_by_its_pettingzoo_view() -> None:
    env = FormationEnv(FormationConfig.task("ch4-individual", max_steps=1))
    with pytest.raises(RuntimeError, match="before reset"):
        env.step_array(np.zeros((3, 2)))
    env.reset(seed=0)
    env.step_array(np.zeros((3, 2)))
    with pytest.raises(RuntimeError, match="finished episode"):
        env.step_array(np.zeros((3, 2)))


def test_a_view_of_a_team_of_a_larger_engine_is_stepped_by_its_engine() -> None:
    engine = FormationEngine([FormationConfig.task("ch4-individual")] * 2)
    view = FormationEnv(engine=engine, team=1)
    view.reset(seed=0)
    assert view.agents == view.possible_agents and engine.live.tolist() == [False, True]
    with pytest.raises(RuntimeError, match="team 1 of an engine of 2 teams"):
        view.step_array(np.zeros((3, 2)))


def test_teams_of_another_task_are_refused() -> None:
    with pytest.raises(ValueError, match="share one task"):
        FormationEngine([FormationConfig.task("ch4-individual"), FormationConfig.task("ch5-bearing")])


def test_a_teams_formation_is_the_pure_geometry_of_its_positions() -> None:
    """``FormationEngine.formation`` after steps equals ``measure_formation`` of the team's positions, an independent
    (numpy-level) route through the same geometry."""
    from sb3_formation.env.geometry import measure_formation, reference_bearings, ring_neighbours

    config = FormationConfig.task("ch5-angle", n_agents=5, stage=3)
    engine = FormationEngine([config.replace(n_agents=4), config])
    engine.reset(0, seed=1)
    engine.reset(1, seed=2)
    rng = np.random.default_rng(3)
    for _ in range(20):
        engine.step(rng.uniform(-1.0, 1.0, (9, 2)))
    positions = engine.team_state(1).positions
    expected = measure_formation(positions, ring_neighbours(5), reference_bearings(5), config.beta_ref_deg, config.d_ref)
    formation = engine.formation(1)
    for name, value in expected._asdict().items():
        np.testing.assert_array_equal(getattr(formation, name), value, err_msg=name)


def test_each_info_column_lands_under_its_key() -> None:
    """The info values' first columns are the keys of ``INFO_KEYS`` that their ``InfoColumn`` names, the reward terms
    follow in the order of ``REWARD_TERMS``, and the contacts' columns are the agent, the obstacle and the rammed
    counts."""
    values = np.arange(2.0 * INFO_VALUES).reshape(2, INFO_VALUES) + 0.5  # row 1, column c holds INFO_VALUES + c + 0.5
    contacts = np.zeros((2, 3), dtype=np.int64)
    contacts[1, ContactColumn.AGENTS], contacts[1, ContactColumn.OBSTACLES], contacts[1, ContactColumn.RAMMED] = 3, 4, 2
    infos = agent_infos(values, contacts, np.array([True, False]))
    assert INFO_VALUES == len(INFO_KEYS) - 4 == InfoColumn.FIRST_TERM + len(REWARD_TERMS)  # less contacts and success
    for column in list(InfoColumn)[:-1]:
        assert infos[1][column.name.lower()] == INFO_VALUES + column + 0.5
    for k, term in enumerate(REWARD_TERMS):
        assert infos[1][f"reward_{term}"] == INFO_VALUES + InfoColumn.FIRST_TERM + k + 0.5
    assert (infos[1]["collisions_agent"], infos[1]["collisions_obstacle"], infos[1]["collisions_rammed"]) == (3, 4, 2)
    assert (infos[0]["success"], infos[1]["success"]) == (True, False)


def test_the_goal_distance_column_is_the_centroids_distance_to_the_goal() -> None:
    """After every step the ``GOAL_DISTANCE`` column (what evaluations record as the final goal distance) holds
    |p^g - p^c| of the team's positions, computed here with numpy's mean; the error columns are the team state's."""
    config = FormationConfig.task("ch5-bearing", stage=3)
    engine = FormationEngine([config, config.replace(n_agents=4)])
    engine.reset(0, seed=1)
    engine.reset(1, seed=2)
    rng = np.random.default_rng(0)
    for _ in range(10):
        step = engine.step(rng.uniform(-1.0, 1.0, (10, 2)))
        for team in (0, 1):
            rows, state = engine.team_rows(team), engine.team_state(team)
            distance = np.hypot(*(state.goal - state.positions.mean(axis=0)))
            np.testing.assert_allclose(step.info_values[rows, InfoColumn.GOAL_DISTANCE], distance, rtol=1e-12)
            np.testing.assert_array_equal(step.info_values[rows, InfoColumn.BEARING_ERROR], state.bearing_errors)
            np.testing.assert_array_equal(step.contacts[rows, ContactColumn.OBSTACLES], state.contacts_obstacle)


@pytest.mark.parametrize("dynamics", ["holonomic", "unicycle"])
def test_a_full_forward_action_from_rest_reaches_v_max_along_the_heading_or_the_action(dynamics: str) -> None:
    """A team alone in open space, at rest: the action (1, 0) is F_max = m v_max / dt, so one step reaches v_max (eq.
    19): along +x for holonomic agents, along the heading (the start faces the goal from the centroid) for unicycles."""
    config = FormationConfig.task("ch5-bearing", stage=3, n_agents=3, dynamics=dynamics)
    engine = FormationEngine([config])
    assert type(engine.dynamics) is {"holonomic": HolonomicDynamics, "unicycle": UnicycleDynamics}[dynamics]
    triangle = np.array([[7.0, 4.0], [8.0, 4.0], [7.5, 4.8]])
    goal = np.array([11.0, 8.0])
    engine.reset(0, scenario=Scenario(triangle, goal))
    step = engine.step(np.tile([1.0, 0.0], (3, 1)))
    if dynamics == "holonomic":
        expected = np.tile([config.v_max, 0.0], (3, 1))
    else:
        facing = math.atan2(*(goal - triangle.mean(axis=0))[::-1])
        expected = np.tile(config.v_max * np.array([math.cos(facing), math.sin(facing)]), (3, 1))
    np.testing.assert_allclose(step.velocities, expected, rtol=0, atol=1e-9 * config.v_max)
    assert not step.contacts.any()


def test_the_goal_progress_is_the_tasks() -> None:
    config = FormationConfig.task("ch5-bearing")
    assert type(FormationEngine([config]).progress) is EuclideanProgress
    assert type(FormationEngine([config.replace(goal_progress="geodesic")]).progress) is GeodesicProgress


def test_no_compiled_function_takes_more_than_twelve_arguments() -> None:
    """Compiled kernels take a few named structures (:mod:`~sb3_formation.env.stacked`, the safety filter's
    ``FilterConstants`` and ``Constraints``), not long lists of parallel arrays: every ``numba.njit`` function of the
    package has at most 12 parameters."""
    import ast
    from pathlib import Path

    import sb3_formation

    crowded = []
    for path in Path(sb3_formation.__file__).parent.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            compiled = isinstance(node, ast.FunctionDef) and any("njit" in ast.unparse(d) for d in node.decorator_list)
            if compiled and len(node.args.args) + len(node.args.kwonlyargs) > 12:
                crowded.append(f"{path.name}:{node.name}")
    assert not crowded, f"compiled functions with more than 12 parameters: {crowded}"
