"""Evaluation: the Wilson interval, evaluate() on fixed-seed episodes (with a tiny PPO and with a scripted policy),
models that do not fit the env, and loading trained models."""

from __future__ import annotations

import csv
import dataclasses
import inspect
import json
import math
import re
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from stable_baselines3 import PPO

from sb3_formation import FormationConfig, FormationEnv, FormationPolicy, make_formation_vec_env
from sb3_formation.controllers import Controller
from sb3_formation.experiment.evaluation import EPISODE_COLUMNS, MAX_RECORDED_EPISODES, evaluate
from sb3_formation.experiment.reports import comparison_table
from sb3_formation.experiment.runs import FINAL_MODEL, FINAL_NORMALIZER, load_trained, save_model
from sb3_formation.experiment.sections import EvaluationSection
from sb3_formation.experiment.statistics import wilson_interval
from sb3_formation.experiment.trajectories import Trajectories
from sb3_formation.sb3.metrics import EPISODE_METRICS
from sb3_formation.sb3.trained import TrainedPolicy
from sb3_formation.utils.files import file_digest

Z95 = 1.959963984540054

# Wilson interval -----------------------------------------------------------------------------------------------------


def wilson_by_quadratic(successes: int, trials: int, z: float = Z95) -> tuple[float, float]:
    """The Wilson bounds as the roots p of (p - p_hat)^2 = z^2 p (1 - p) / n, i.e.
    (1 + z^2/n) p^2 - (2 p_hat + z^2/n) p + p_hat^2 = 0 (a derivation independent of the centre/half-width form)."""
    p_hat = successes / trials
    a, b, c = 1 + z * z / trials, -(2 * p_hat + z * z / trials), p_hat * p_hat
    root = math.sqrt(max(b * b - 4 * a * c, 0.0))
    return (-b - root) / (2 * a), (-b + root) / (2 * a)


@pytest.mark.parametrize(
    ("successes", "trials", "low", "high"),
    [
        # z^2 = 1.959963984540054^2 = 3.841459, so z^2/n = 0.3841459 and 1 + z^2/n = 1.3841459 for n = 10.
        # 0/10: p_hat = 0, the quadratic is 1.3841459 p^2 - 0.3841459 p = 0, roots 0 and 0.3841459 / 1.3841459 = 0.277533
        (0, 10, 0.0, 0.277533),
        # 5/10: centre (0.5 + z^2/20) / 1.3841459 = 0.6920729 / 1.3841459 = 0.5; half-width
        # z sqrt(0.5 * 0.5 / 10 + z^2 / 400) / 1.3841459 = 1.959964 * sqrt(0.025 + 0.0096036) / 1.3841459
        # = 1.959964 * 0.1860204 / 1.3841459 = 0.263407, so 0.5 -/+ 0.263407
        (5, 10, 0.236593, 0.763407),
        # 10/10: the mirror image of 0/10: 1 - 0.277533 = 0.722467, and 1
        (10, 10, 0.722467, 1.0),
    ],
)
def test_wilson_interval_matches_hand_computed_values(successes: int, trials: int, low: float, high: float) -> None:
    assert wilson_interval(successes, trials) == pytest.approx((low, high), abs=1e-6)


@pytest.mark.parametrize("trials", [1, 3, 6, 7, 10, 13, 25, 100])
def test_wilson_interval_contains_the_observed_rate(trials: int) -> None:
    for successes in range(1, trials):
        low, high = wilson_interval(successes, trials)
        assert 0.0 < low < successes / trials < high < 1.0


@pytest.mark.parametrize("trials", [3, 10])
def test_wilson_interval_is_exact_at_the_ends(trials: int) -> None:
    assert wilson_interval(0, trials)[0] == 0.0
    assert wilson_interval(trials, trials)[1] == 1.0


@pytest.mark.parametrize(("successes", "trials"), [(0, 1), (1, 1), (3, 7), (1, 3), (99, 100), (500, 1000)])
def test_wilson_interval_solves_the_wilson_quadratic(successes: int, trials: int) -> None:
    assert wilson_interval(successes, trials) == pytest.approx(wilson_by_quadratic(successes, trials), abs=1e-12)


def test_wilson_interval_narrows_with_trials_and_follows_z() -> None:
    widths = [np.diff(wilson_interval(n // 2, n))[0] for n in (10, 100, 1000)]
    assert widths[0] > widths[1] > widths[2] > 0
    assert wilson_interval(5, 10, z=0.0) == pytest.approx((0.5, 0.5))
    low99, high99 = wilson_interval(5, 10, z=2.5758293035489)
    assert low99 < 0.236593 and high99 > 0.763407


@pytest.mark.parametrize(("successes", "trials"), [(0, 0), (1, 0), (-1, 10), (11, 10), (0, -3)])
def test_wilson_interval_rejects_invalid_counts(successes: int, trials: int) -> None:
    with pytest.raises(ValueError, match="successes"):
        wilson_interval(successes, trials)


# A tiny trained model ------------------------------------------------------------------------------------------------

MAX_STEPS = 30
SMALL_NETS = {"net_arch": {"pi": [16], "vf": [16]}}


@pytest.fixture(scope="module")
def tiny() -> Iterator[SimpleNamespace]:
    """A PPO with small nets trained for one iteration, as a TrainedPolicy built by hand, and its normalised env."""
    env = make_formation_vec_env("ch5-bearing", n_envs=1, seed=0, max_steps=MAX_STEPS)
    model = PPO(FormationPolicy, env, n_steps=8, batch_size=24, n_epochs=1, seed=0, device="cpu", policy_kwargs=SMALL_NETS)
    model.learn(8 * env.num_envs)
    trained = TrainedPolicy(model, env.venv.config, env.state_dict())
    yield SimpleNamespace(trained=trained, env=env)
    env.close()


def comparable(episodes: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{key: value for key, value in episode.items() if key != "team"} for episode in episodes]


def check_summary(summary: dict[str, Any], episodes: list[dict[str, Any]]) -> None:
    """The summary agrees with the per-episode list (means and population stds recomputed with numpy)."""
    successful = [episode for episode in episodes if episode["success"]]
    assert summary["episodes"] == len(episodes)
    assert summary["successes"] == len(successful)
    assert summary["success_rate"] == len(successful) / len(episodes)
    assert summary["success_rate_ci95"] == list(wilson_interval(len(successful), len(episodes)))
    for key, group in (("successful_episodes", successful), ("all_episodes", episodes)):
        assert set(summary[key]) == set(EPISODE_METRICS)
        for name, statistics in summary[key].items():
            if group:
                values = np.array([episode[name] for episode in group], dtype=np.float64)
                assert statistics["mean"] == pytest.approx(values.sum() / len(values), rel=1e-12, abs=1e-15)
                assert statistics["std"] == pytest.approx(math.sqrt(((values - values.mean()) ** 2).mean()), abs=1e-12)
            else:
                assert statistics == {"mean": None, "std": None}


def test_evaluate_summary_agrees_with_its_episodes(tiny: SimpleNamespace) -> None:
    result = evaluate(tiny.trained, episodes=5, stage=3, seed=11, n_envs=2)
    assert len(result.episodes) == 5
    assert (result.stage, result.seed, result.deterministic) == (3, 11, True)
    summary = result.summary
    assert (summary["stage"], summary["seed"], summary["deterministic"]) == (3, 11, True)
    check_summary(summary, result.episodes)
    # stage 3 starts metres from the goal and an agent moves 1.5 cm per step: every episode is a time-out
    assert summary["successes"] == 0 and summary["success_rate_ci95"][0] == 0.0
    assert [episode["length"] for episode in result.episodes] == [MAX_STEPS] * 5
    assert all(episode["stage"] == 3 for episode in result.episodes)
    # two teams with a quota of 3 each, interleaved and cut to 5
    assert [episode["team"] for episode in result.episodes] == [0, 1, 0, 1, 0]


@pytest.mark.parametrize(("episodes", "n_envs"), [(1, 8), (3, 8), (4, 2), (5, 3)])
def test_evaluate_plays_exactly_the_requested_episodes(tiny: SimpleNamespace, episodes: int, n_envs: int) -> None:
    result = evaluate(tiny.trained, episodes=episodes, stage=1, seed=2, n_envs=n_envs, env_overrides={"max_steps": 4})
    assert len(result.episodes) == episodes == result.summary["episodes"]
    n_teams = min(episodes, n_envs)
    assert [episode["team"] for episode in result.episodes] == [k % n_teams for k in range(episodes)]
    assert all(episode["length"] == 4 and episode["stage"] == 1 for episode in result.episodes)


def test_evaluate_is_reproducible_by_seed(tiny: SimpleNamespace) -> None:
    first = evaluate(tiny.trained, episodes=4, stage=3, seed=5, n_envs=2)
    again = evaluate(tiny.trained, episodes=4, stage=3, seed=5, n_envs=2)
    other = evaluate(tiny.trained, episodes=4, stage=3, seed=7, n_envs=2)
    assert first.episodes == again.episodes
    assert first.summary == again.summary
    assert comparable(first.episodes) != comparable(other.episodes)
    for mine, theirs in zip(first.episodes, other.episodes):
        assert mine["angle_error_deg"] != theirs["angle_error_deg"]  # other scenarios, other errors


def test_evaluate_rejects_no_episodes(tiny: SimpleNamespace) -> None:
    with pytest.raises(ValueError, match="episodes"):
        evaluate(tiny.trained, episodes=0)


# A scripted policy that reaches the goal -----------------------------------------------------------------------------


class TowardsGoal(Controller):
    """A plain scripted controller: every agent pushes at full force along the centroid-to-goal offset it observes.
    The raw observations it saw and the actions it took are recorded."""

    def __init__(self, config: FormationConfig) -> None:
        super().__init__(config)
        self.seen: list[np.ndarray] = []
        self.actions: list[np.ndarray] = []

    def act(self, observations: np.ndarray, agents: np.ndarray, deterministic: bool) -> np.ndarray:
        assert deterministic
        offset = observations[:, self.layout["centroid_goal_offset"]]
        actions = offset / np.maximum(np.linalg.norm(offset, axis=1, keepdims=True), 1e-12)
        self.seen.append(observations.copy())
        self.actions.append(actions)
        return actions


class RecordingPredictor:
    """A stand-in for an SB3 policy behind a :class:`TrainedPolicy`: it records the (normalised) observations it gets
    and pushes along the centroid-to-goal offset it sees (the scale is the same for both components)."""

    def __init__(self, offset: slice) -> None:
        self.offset = offset
        self.seen: list[np.ndarray] = []
        self.actions: list[np.ndarray] = []

    def predict(
        self, observation: np.ndarray, state: Any = None, episode_start: np.ndarray | None = None, deterministic: bool = True
    ) -> tuple[np.ndarray, None]:
        offset = observation[:, self.offset].astype(np.float64)
        actions = (offset / np.maximum(np.linalg.norm(offset, axis=1, keepdims=True), 1e-12)).astype(np.float32)
        self.seen.append(observation.copy())
        self.actions.append(actions)
        return actions, None


def scripted(tiny: SimpleNamespace) -> TowardsGoal:
    """The scripted controller in the tiny model's task."""
    return TowardsGoal(tiny.trained.config)


# v_max 1 m/s: 30 cm per step, so the 6 m or more from a stage-3 start to the goal take about 25 steps
FAST = {"v_max": 1.0, "max_steps": 100}


@pytest.mark.parametrize("stage", [1, 3])
def test_evaluate_counts_successes_of_a_policy_that_reaches_the_goal(tiny: SimpleNamespace, stage: int) -> None:
    trained = scripted(tiny)  # the controller sees raw observations
    result = evaluate(trained, episodes=6, stage=stage, seed=3, n_envs=3, env_overrides=FAST)
    assert all(episode["success"] for episode in result.episodes)
    assert all(episode["length"] < FAST["max_steps"] for episode in result.episodes)  # ended by the goal, not time
    summary = result.summary
    assert summary["successes"] == 6 and summary["success_rate"] == 1.0
    assert summary["success_rate_ci95"] == pytest.approx([wilson_interval(6, 6)[0], 1.0])
    check_summary(summary, result.episodes)
    for name in EPISODE_METRICS:
        assert summary["successful_episodes"][name] == summary["all_episodes"][name]


def test_evaluate_mixes_successes_and_time_outs(tiny: SimpleNamespace) -> None:
    """With too few steps for the farther starts some episodes fail; the means cover only the successful ones."""
    trained = scripted(tiny)
    lengths = [e["length"] for e in evaluate(trained, episodes=8, stage=1, seed=3, n_envs=4, env_overrides=FAST).episodes]
    cut = int(np.median(lengths))  # about half of these episodes need more steps than this
    result = evaluate(trained, episodes=8, stage=1, seed=3, n_envs=4, env_overrides={**FAST, "max_steps": cut})
    outcomes = [episode["success"] for episode in result.episodes]
    assert any(outcomes) and not all(outcomes)
    assert [episode["success"] for episode in result.episodes] == [length <= cut for length in lengths]
    check_summary(result.summary, result.episodes)
    successful_lengths = [length for length in lengths if length <= cut]
    assert result.summary["successful_episodes"]["length"]["mean"] == pytest.approx(np.mean(successful_lengths))


def test_evaluate_normalises_with_the_stored_statistics_frozen(tiny: SimpleNamespace) -> None:
    """The policy sees the raw observations divided by sqrt(var + epsilon) (flags untouched), for the whole evaluation."""
    state = dict(tiny.env.state_dict())
    state["var"] = np.full_like(state["var"], 4.0)  # every feature divided by sqrt(4 + epsilon)
    state["count"] = np.array(1.0)
    state["clip_obs"] = np.array(np.nan)  # no clipping: offsets of several metres stay as they are
    policy = RecordingPredictor(tiny.env.venv.observation_layout["centroid_goal_offset"])
    trained = TrainedPolicy(policy, tiny.trained.config, state)
    result = evaluate(trained, episodes=2, stage=3, seed=9, n_envs=1, env_overrides=FAST)
    assert all(episode["success"] for episode in result.episodes)
    # replay the policy's actions on a raw env: episode k starts from reset(seed=9 + k)
    env = FormationEnv(trained.config.replace(**FAST, stage=3))
    observations, actions = [], iter(policy.actions)
    for episode in range(2):
        team, _ = env.reset(seed=9 + episode)
        observations.append(np.stack(list(team.values())))
        while env.agents:
            team, *_ = env.step(dict(zip(env.agents, next(actions))))
            if env.agents:
                observations.append(np.stack(list(team.values())))
    scale = np.where(tiny.env.venv.binary_observation_mask, 1.0, math.sqrt(4.0 + float(trained.normalizer_state["epsilon"])))
    assert len(policy.seen) == len(observations) == sum(episode["length"] for episode in result.episodes) > 20
    for seen, expected in zip(policy.seen, observations):
        np.testing.assert_allclose(seen, (expected / scale).astype(np.float32), rtol=1e-6, atol=1e-7)


# Models that do not fit -----------------------------------------------------------------------------------------------


def test_evaluate_rejects_a_team_size_the_model_was_not_trained_for(tiny: SimpleNamespace) -> None:
    assert tiny.trained.config.n_agents == 6
    with pytest.raises(ValueError, match=r"n_agents=6 in the model, 3 in the env"):
        evaluate(tiny.trained, episodes=2, env_overrides={"n_agents": 3})


def test_a_trained_policy_fits_only_envs_of_its_observation_layout(tiny: SimpleNamespace) -> None:
    config = tiny.trained.config
    assert tiny.trained.fit(config) is tiny.trained  # fits
    assert tiny.trained.fit(config.replace(max_steps=7, stage=3, v_max=0.5)) is tiny.trained  # observation size unchanged
    with pytest.raises(ValueError) as raised:
        tiny.trained.fit(config.replace(n_agents=3, lidar_rays=45))
    message = str(raised.value)
    assert "n_agents=6 in the model, 3 in the env" in message
    assert "lidar_rays=90 in the model, 45 in the env" in message


# Loading trained models ----------------------------------------------------------------------------------------------


def test_load_trained_needs_a_model_in_the_folder(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=re.escape(str(tmp_path))):
        load_trained(tmp_path)
    missing = tmp_path / "nowhere.zip"
    with pytest.raises(FileNotFoundError, match=re.escape(str(missing))):
        load_trained(missing)


def test_load_trained_needs_the_normaliser_beside_the_model(tiny: SimpleNamespace, tmp_path: Path) -> None:
    path = tmp_path / "model.zip"
    tiny.trained.model.save(path)
    with pytest.raises(FileNotFoundError, match=re.escape(str(tmp_path / FINAL_NORMALIZER))):
        load_trained(path)


def test_load_trained_round_trips_a_saved_model(tiny: SimpleNamespace, tmp_path: Path) -> None:
    model = tiny.trained.model
    model.formation_config = dataclasses.asdict(tiny.trained.config)  # as training.train() does
    save_model(model, tiny.env, tmp_path, FINAL_MODEL, FINAL_NORMALIZER)
    for path in (tmp_path, tmp_path / FINAL_MODEL):
        loaded = load_trained(path, device="cpu")
        assert loaded.config == tiny.trained.config
        assert loaded.team_observations is False
        assert set(loaded.normalizer_state) == set(tiny.trained.normalizer_state)
        for key, value in tiny.trained.normalizer_state.items():
            np.testing.assert_array_equal(loaded.normalizer_state[key], value)
    original = evaluate(tiny.trained, episodes=2, stage=3, seed=4, n_envs=2)
    assert evaluate(loaded, episodes=2, stage=3, seed=4, n_envs=2).episodes == original.episodes


# Episode files and trajectories --------------------------------------------------------------------------------------


def recomputed_from_trajectories(trajectories: Trajectories, index: int) -> dict[str, Any]:
    """An episode's row as recomputed from its recorded steps: means over steps 1..T of the means over agents, contact
    totals, and the neighbour distances > d_comm from the positions (ring neighbours i - 1, i + 1)."""
    steps = trajectories.steps(index)
    config = trajectories.config
    positions = steps["positions"][1:]
    succeeding = np.roll(positions, -1, axis=1)
    comm_exceeded = (np.linalg.norm(succeeding - positions, axis=2) > config.d_comm).any(axis=1)
    centroids = steps["positions"].mean(axis=1)
    return {
        "length": len(positions),
        "success": bool(trajectories.success[index]),
        "angle_error_deg": steps["angle_error_deg"][1:].mean(),
        "bearing_error": steps["bearing_error"][1:].mean(),
        "neighbour_distance_error": steps["neighbour_distance_error"][1:].mean(),
        "collisions_obstacle": int(steps["collisions_obstacle"][1:].sum()),
        "collisions_agent": int(steps["collisions_agent"][1:].sum()) // 2,
        "comm_exceeded_fraction": comm_exceeded.mean(),
        "final_goal_distance": float(np.linalg.norm(centroids[-1] - trajectories.goals[index])),
        "goal_distance": np.linalg.norm(centroids - trajectories.goals[index], axis=1),
    }


@pytest.fixture(scope="module")
def wandering(tiny: SimpleNamespace, tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    """The tiny PPO sampling its actions at 1 m/s: agents wander apart (beyond d_comm), some touch; all episodes saved."""
    result = evaluate(
        tiny.trained, episodes=4, stage=1, seed=21, n_envs=2, deterministic=False, env_overrides=WANDER, record=4
    )
    folder = tmp_path_factory.mktemp("eval")
    return SimpleNamespace(result=result, folder=folder, files=result.save(folder))


WANDER = {"v_max": 1.0, "max_steps": 40}


def test_episode_rows_match_their_recorded_trajectories(wandering: SimpleNamespace) -> None:
    result, trajectories = wandering.result, wandering.result.trajectories
    assert trajectories is not None and trajectories.episodes.tolist() == [0, 1, 2, 3]
    assert trajectories.seeds.tolist() == [21, 22, 23, 24]
    assert sum(row["comm_exceeded_fraction"] > 0 for row in result.episodes) >= 1  # the check is not vacuous
    for index, row in enumerate(result.episodes):
        expected = recomputed_from_trajectories(trajectories, index)
        np.testing.assert_allclose(trajectories.steps(index)["goal_distance"], expected.pop("goal_distance"), atol=1e-9)
        for name, value in expected.items():
            assert row[name] == pytest.approx(value, rel=1e-9, abs=1e-12), name
        # the padding after the episode's end is NaN and row 0 has no errors or actions
        assert np.isnan(trajectories.angle_error_deg[index, 0]).all() and np.isnan(trajectories.actions[index, 0]).all()
        assert np.isnan(trajectories.positions[index, row["length"] + 1 :]).all()
    check_summary(result.summary, result.episodes)


def test_recorded_steps_replay_in_a_fresh_env(wandering: SimpleNamespace) -> None:
    """Positions and goal/obstacles of a recorded episode are what the env gives for its seed and recorded actions."""
    trajectories = wandering.result.trajectories
    env = FormationEnv(trajectories.config)
    for index in range(len(trajectories)):
        env.reset(seed=int(trajectories.seeds[index]))
        np.testing.assert_array_equal(env.goal, trajectories.goals[index])
        np.testing.assert_array_equal(
            env.obstacles, trajectories.obstacles[index][~np.isnan(trajectories.obstacles[index, :, 0])]
        )
        steps = trajectories.steps(index)
        for actions, positions in zip(steps["actions"][1:], steps["positions"][1:]):
            env.step(dict(zip(env.agents, actions)))
            np.testing.assert_array_equal(env.world.positions, positions)
        assert not env.agents


def test_saved_files_hold_the_summary_rows_and_trajectories(wandering: SimpleNamespace) -> None:
    result, files = wandering.result, wandering.files
    assert set(files) == {"summary", "episodes", "trajectories"}
    stored = json.loads(files["summary"].read_text())
    assert stored.pop("files") == {
        name: file_digest(files[kind]) for kind, name in (("episodes", "episodes.csv"), ("trajectories", "trajectories.npz"))
    }
    assert stored == result.summary
    with open(files["episodes"], newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert list(rows[0]) == list(EPISODE_COLUMNS)
    assert [int(row["episode"]) for row in rows] == [0, 1, 2, 3]
    for row, episode in zip(rows, result.episodes):
        assert row["success"] == str(episode["success"])
        for name in ("length", "collisions_obstacle", "collisions_agent", "seed", "team"):
            assert int(row[name]) == episode[name]
        for name in ("angle_error_deg", "comm_exceeded_fraction", "return", "reward_goal"):
            assert float(row[name]) == episode[name]  # repr round-trips floats exactly
    loaded = Trajectories.load(files["trajectories"])
    assert loaded.config == result.trajectories.config
    for item in dataclasses.fields(Trajectories):
        if item.name != "config":
            np.testing.assert_array_equal(getattr(loaded, item.name), getattr(result.trajectories, item.name))


def test_saving_an_evaluation_without_trajectories_removes_older_ones(wandering: SimpleNamespace) -> None:
    files = dataclasses.replace(wandering.result, trajectories=None).save(wandering.folder / "again")
    assert "trajectories" not in files
    wandering.result.save(wandering.folder / "again")
    assert (wandering.folder / "again" / "trajectories.npz").exists()
    dataclasses.replace(wandering.result, trajectories=None).save(wandering.folder / "again")
    assert not (wandering.folder / "again" / "trajectories.npz").exists()


def test_only_the_first_episodes_are_recorded(tiny: SimpleNamespace) -> None:
    result = evaluate(tiny.trained, episodes=5, stage=1, seed=2, n_envs=2, env_overrides={"max_steps": 6}, record=2)
    assert result.trajectories.episodes.tolist() == [0, 1]
    assert result.trajectories.positions.shape == (2, 7, 6, 2)
    assert evaluate(tiny.trained, episodes=2, stage=1, seed=2, env_overrides={"max_steps": 6}, record=0).trajectories is None


def test_trajectories_load_names_a_bad_file(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"nothing\.npz"):
        Trajectories.load(tmp_path / "nothing.npz")
    bad = tmp_path / "bad.npz"
    np.savez(bad, positions=np.zeros(3))
    with pytest.raises(ValueError, match=r"bad\.npz"):
        Trajectories.load(bad)


# Seeds, teams and workers --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("n_envs", "n_workers"), [(1, 1), (3, 1), (2, 2)])
def test_episode_k_plays_the_scenario_of_seed_plus_k(tiny: SimpleNamespace, n_envs: int, n_workers: int) -> None:
    result = evaluate(tiny.trained, episodes=5, stage=3, seed=40, n_envs=n_envs, n_workers=n_workers, record=5)
    env = FormationEnv(tiny.trained.config.replace(stage=3))
    for index in range(5):
        env.reset(seed=40 + index)
        np.testing.assert_array_equal(result.trajectories.goals[index], env.goal)
        np.testing.assert_array_equal(result.trajectories.positions[index, 0], env.world.positions)


def test_worker_processes_give_the_same_episodes_for_a_batch_independent_policy(tiny: SimpleNamespace) -> None:
    """A policy acting row by row (numpy) is unaffected by how teams are batched: 1 or 3 teams agree, and 2 processes
    give 1 process's rows exactly, teams included (the policy acts in this process; workers only step teams)."""
    trained = scripted(tiny)
    runs = [
        evaluate(trained, episodes=5, stage=1, seed=3, n_envs=n_envs, n_workers=n_workers, env_overrides=FAST)
        for n_envs, n_workers in ((1, 1), (3, 1), (3, 2))
    ]
    for run in runs[1:]:
        assert comparable(run.episodes) == comparable(runs[0].episodes)
        assert run.summary == runs[0].summary
    assert runs[2].episodes == runs[1].episodes and {row["team"] for row in runs[2].episodes} == {0, 1, 2}


class Failing(TowardsGoal):
    def act(self, observations: np.ndarray, agents: np.ndarray, deterministic: bool) -> np.ndarray:
        raise ArithmeticError("policy exploded")


def test_a_failing_policy_is_reported_with_workers(tiny: SimpleNamespace) -> None:
    with pytest.raises(ArithmeticError, match="policy exploded"):
        evaluate(Failing(tiny.trained.config), episodes=2, stage=1, seed=3, n_envs=2, n_workers=2, env_overrides=FAST)


def test_stochastic_evaluation_is_seeded(tiny: SimpleNamespace) -> None:
    first = evaluate(tiny.trained, episodes=2, stage=1, seed=8, deterministic=False, env_overrides=WANDER)
    again = evaluate(tiny.trained, episodes=2, stage=1, seed=8, deterministic=False, env_overrides=WANDER)
    greedy = evaluate(tiny.trained, episodes=2, stage=1, seed=8, deterministic=True, env_overrides=WANDER)
    assert first.episodes == again.episodes
    assert comparable(first.episodes) != comparable(greedy.episodes)
    assert first.summary["deterministic"] is False


def test_evaluate_rejects_bad_worker_and_record_counts(tiny: SimpleNamespace) -> None:
    with pytest.raises(ValueError, match="n_workers"):
        evaluate(tiny.trained, episodes=2, n_envs=2, n_workers=3)
    with pytest.raises(ValueError, match="record"):
        evaluate(tiny.trained, episodes=2, record=-1)


def test_the_evaluation_section_is_the_protocol_of_evaluate() -> None:
    """Every field of the recipe's evaluation protocol is a keyword of evaluate(), under the same name; command-line
    changes are validated by the section, with the message evaluate() gives for too many recorded episodes."""
    keywords = inspect.signature(evaluate).parameters
    assert all(item.name in keywords for item in dataclasses.fields(EvaluationSection))
    protocol = EvaluationSection(episodes=4, stage=3, seed=2, n_envs=2, deterministic=False, record=1)
    assert protocol.kwargs() == {"episodes": 4, "stage": 3, "seed": 2, "n_envs": 2, "deterministic": False, "record": 1}
    assert EvaluationSection(episodes=4).kwargs() == {"episodes": 4}  # unset: evaluate()'s default
    for record in (-1, MAX_RECORDED_EPISODES + 1):
        with pytest.raises(
            ValueError, match=re.escape(f"evaluation: record (--trajectories) must be in [0, 100], got {record}")
        ):
            protocol.replace(record=record)
    with pytest.raises(ValueError, match="evaluation: n_envs must be an integer >= 1, got 0"):
        protocol.replace(n_envs=0)


def test_comparison_table_rows_hold_rate_interval_and_mean_std() -> None:
    def summary(successes: int, angle: float | None) -> dict[str, Any]:
        statistics = {name: {"mean": None, "std": None} for name in EPISODE_METRICS}
        if angle is not None:
            statistics = {name: {"mean": 2.0, "std": 0.5} for name in EPISODE_METRICS}
            statistics["angle_error_deg"] = {"mean": angle, "std": 3.25}
            statistics["length"] = {"mean": 1234.4, "std": 101.0}
        return {
            "episodes": 10,
            "success_rate": successes / 10,
            "success_rate_ci95": list(wilson_interval(successes, 10)),
            "successful_episodes": statistics,
        }

    lines = comparison_table({"team": summary(5, 31.25), "individual": summary(0, None)}).splitlines()
    assert lines[0] == (
        "| policy | episodes | success rate (95 % CI) | angle error (deg) | bearing error | distance error (m) | steps "
        "| obstacle collisions | agent collisions |"
    )
    # 5/10: Wilson 23.7 % - 76.3 % (hand-computed above); 31.25 -> one decimal, 1234.4 -> whole, 2.0 -> 3 digits
    assert (
        lines[2] == "| team | 10 | 50.0% (23.7% - 76.3%) | 31.2 ± 3.25 | 2 ± 0.5 | 2 ± 0.5 | 1234 ± 101 | 2 ± 0.5 | 2 ± 0.5 |"
    )
    assert lines[3] == "| individual | 10 | 0.0% (0.0% - 27.8%) | - | - | - | - | - | - |"
    with pytest.raises(ValueError, match="over"):
        comparison_table({}, over="some")


class StepCounter:
    """A stand-in for a recurrent policy: its state counts each slot's steps since its last episode start, and its
    actions push towards the goal as :class:`TowardsGoal` does (so episodes end at different steps)."""

    def __init__(self, towards_goal: TowardsGoal) -> None:
        self.towards_goal = towards_goal
        self.config = towards_goal.config
        self.calls: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (episode_start, state in, state out)

    def predict(
        self, observation: np.ndarray, state: Any = None, episode_start: np.ndarray | None = None, deterministic: bool = True
    ) -> tuple[np.ndarray, tuple[np.ndarray]]:
        counts = np.zeros(len(observation)) if state is None else state[0].copy()
        counts[episode_start] = 0
        self.calls.append((episode_start.copy(), counts.copy(), counts + 1))
        return self.towards_goal.predict(observation)[0], (counts + 1,)

    def fit(self, config: FormationConfig) -> StepCounter:
        return self


def test_evaluate_carries_recurrent_states_and_flags_episode_starts(tiny: SimpleNamespace) -> None:
    counter = StepCounter(scripted(tiny))
    result = evaluate(counter, episodes=5, stage=1, seed=3, n_envs=2, env_overrides=FAST)
    n_agents = counter.config.n_agents
    assert counter.calls[0][0].all()  # every slot starts an episode at the first call
    for (_, _, returned), (starts, received, _) in zip(counter.calls, counter.calls[1:]):
        np.testing.assert_array_equal(received, np.where(starts, 0, returned))  # the state comes back, reset at starts
    # each team's slots start together, and each episode's start is flagged once: 5 episodes x 6 agents in all
    flags = np.array([starts for starts, _, _ in counter.calls])
    assert (flags.reshape(len(flags), -1, n_agents).all(axis=2) == flags.reshape(len(flags), -1, n_agents).any(axis=2)).all()
    assert flags.sum() == 5 * n_agents
    # slot 0's count just before each restart of team 0 is the length of team 0's episode that just ended
    lengths = [int(call[2][0]) for call, following in zip(counter.calls, counter.calls[1:]) if following[0][0]]
    team_lengths = [episode["length"] for episode in result.episodes if episode["team"] == 0]
    assert len(team_lengths) >= 2 and lengths == team_lengths[:-1]  # the last one ends with no restart
