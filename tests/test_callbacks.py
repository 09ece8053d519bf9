"""SB3 callbacks: the curriculum schedule (by iterations and early by success rate), formation metrics in TensorBoard
(read back with TensorBoard's own event reader), and the progress bar."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import torch as th
from logged_names import EPISODE_SCALARS
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.logger import configure
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins.custom_scalar import layout_pb2
from tensorboard_events import read_hparams

from sb3_formation import REWARD_TERMS, FormationPolicy, make_formation_vec_env
from sb3_formation.sb3.callbacks import (
    HPARAM_METRICS,
    CollectionThreadsCallback,
    CurriculumCallback,
    FormationMetricsCallback,
    IterationProgressCallback,
    custom_scalars_layout,
    hparam_values,
)

N_AGENTS = 6  # ch5-bearing
N_STEPS = 8
SMALL_NETS = {"net_arch": {"pi": [16], "vf": [16]}}


def tiny_ppo(n_envs: int, max_steps: int, seed: int = 0, **env_kwargs: Any) -> PPO:
    env = make_formation_vec_env("ch5-bearing", n_envs=n_envs, seed=seed, max_steps=max_steps, **env_kwargs)
    return PPO(
        FormationPolicy,
        env,
        n_steps=N_STEPS,
        batch_size=24,
        n_epochs=1,
        seed=seed,
        device="cpu",
        policy_kwargs=SMALL_NETS,
    )


def learn_iterations(model: PPO, iterations: int, callbacks: list[BaseCallback]) -> None:
    model.learn(iterations * N_STEPS * model.get_env().num_envs, callback=CallbackList(callbacks))


def read_events(folder: Path) -> EventAccumulator:
    events = EventAccumulator(str(folder), size_guidance={"scalars": 0, "tensors": 0})
    events.Reload()
    return events


def scalars(events: EventAccumulator, tag: str) -> dict[int, float]:
    return {event.step: event.value for event in events.Scalars(tag)}


class StageRecorder(BaseCallback):
    """Every team's curriculum stage at the start and at the end of each rollout (put it before the curriculum)."""

    def __init__(self) -> None:
        super().__init__()
        self.at_start: list[list[int]] = []
        self.at_end: list[list[int]] = []

    def _on_rollout_start(self) -> None:
        self.at_start.append(self.training_env.get_attr("stage"))

    def _on_step(self) -> bool:
        return True

    def _on_rollout_end(self) -> None:
        self.at_end.append(self.training_env.get_attr("stage"))


# CurriculumCallback in a real PPO run ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def curriculum_run(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    """5 iterations of a tiny PPO (2 teams) under iterations_per_stage=(2, 1, 2), logged to TensorBoard.

    The callbacks are those of a training run (``training._learn``): the curriculum, then the metrics (which log the
    stage every iteration); the recorder comes first, so it sees the stage each rollout ran in.
    """
    folder = tmp_path_factory.mktemp("curriculum")
    model = tiny_ppo(n_envs=2, max_steps=20)
    model.set_logger(configure(str(folder), ["tensorboard"]))
    recorder, curriculum = StageRecorder(), CurriculumCallback((2, 1, 2))
    learn_iterations(model, 5, [recorder, curriculum, FormationMetricsCallback()])
    model.logger.close()
    steps_per_iteration = N_STEPS * 2 * N_AGENTS
    return SimpleNamespace(
        model=model,
        recorder=recorder,
        curriculum=curriculum,
        events=read_events(folder),
        iteration_steps=[steps_per_iteration * k for k in range(1, 6)],
    )


def test_curriculum_runs_each_stage_for_its_iterations_on_every_team(curriculum_run: SimpleNamespace) -> None:
    recorder, curriculum = curriculum_run.recorder, curriculum_run.curriculum
    expected = [1, 1, 2, 3, 3]  # stage 1 for iterations 1-2, stage 2 for iteration 3, stage 3 for iterations 4-5
    n_slots = 2 * N_AGENTS
    assert recorder.at_start == [[stage] * n_slots for stage in expected]
    assert recorder.at_end == [[stage] * n_slots for stage in expected]  # unchanged during each rollout
    assert curriculum.iteration == 5 and curriculum.stage == 3 and curriculum.stage_iteration == 2
    assert curriculum.total_iterations == 5
    assert curriculum_run.model.num_timesteps == curriculum_run.iteration_steps[-1]
    assert curriculum_run.model.get_env().get_attr("stage") == [3] * n_slots  # stays in stage 3 at the end


def test_curriculum_stage_is_logged_once_per_iteration(curriculum_run: SimpleNamespace) -> None:
    logged = scalars(curriculum_run.events, "curriculum/stage")
    assert sorted(logged) == curriculum_run.iteration_steps
    assert set(logged.values()) <= {1.0, 2.0, 3.0}
    assert logged[curriculum_run.iteration_steps[0]] == 1.0 and logged[curriculum_run.iteration_steps[-1]] == 3.0
    values = [logged[step] for step in curriculum_run.iteration_steps]
    assert values == sorted(values)  # never goes back


def test_logged_curriculum_stage_is_the_stage_of_the_logged_iteration(curriculum_run: SimpleNamespace) -> None:
    logged = scalars(curriculum_run.events, "curriculum/stage")
    rollout_stages = [float(stages[0]) for stages in curriculum_run.recorder.at_end]
    assert rollout_stages == [1.0, 1.0, 2.0, 3.0, 3.0]
    assert [logged.get(step) for step in curriculum_run.iteration_steps] == rollout_stages


def test_curriculum_state_round_trips_through_json(curriculum_run: SimpleNamespace) -> None:
    state = curriculum_run.curriculum.state_dict()
    assert state == {"stage": 3, "iteration": 5, "stage_iteration": 2, "successes": state["successes"]}
    restored = CurriculumCallback((2, 1, 2))
    restored.load_state_dict(json.loads(json.dumps(state)))  # checkpoints store it as JSON
    assert restored.state_dict() == state


# CurriculumCallback driven by hand -----------------------------------------------------------------------------------


class FakeTeams:
    """A stand-in training env: ``n_teams`` teams of ``n_agents`` slots, with SB3's ``env_method`` / ``get_attr``."""

    def __init__(self, n_teams: int = 2, n_agents: int = 3) -> None:
        self.n_agents = n_agents
        self.team_stages = [1] * n_teams
        self.calls: list[tuple[str, tuple]] = []

    @property
    def num_envs(self) -> int:
        return len(self.team_stages) * self.n_agents

    def env_method(self, name: str, *args: Any, indices: Any = None, **kwargs: Any) -> list[Any]:
        self.calls.append((name, args))
        assert name == "set_stage" and indices is None and not kwargs
        self.team_stages = [args[0]] * len(self.team_stages)
        return [None] * self.num_envs

    def get_attr(self, name: str, indices: Any = None) -> list[Any]:
        assert name == "stage"
        return [stage for stage in self.team_stages for _ in range(self.n_agents)]

    def infos(self, *episodes: tuple[int, bool]) -> list[dict[str, Any]]:
        """One step's infos in which team j ends an episode (stage, success) = episodes[j] (None: no episode ends)."""
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for team, episode in enumerate(episodes):
            if episode is not None:
                stage, success = episode
                infos[team * self.n_agents]["formation_episode"] = {"stage": stage, "success": success, "length": 7}
        return infos


class FakeLogger:
    def __init__(self) -> None:
        self.records: list[tuple[str, Any]] = []

    def record(self, key: str, value: Any, exclude: Any = None) -> None:
        self.records.append((key, value))


def driven(callback: CurriculumCallback) -> tuple[CurriculumCallback, FakeTeams, FakeLogger]:
    """``callback`` attached to a fake model, training started."""
    teams, logger = FakeTeams(), FakeLogger()
    callback.init_callback(SimpleNamespace(get_env=lambda: teams, logger=logger, num_timesteps=0))
    callback.on_training_start({}, {})
    return callback, teams, logger


def feed(callback: CurriculumCallback, teams: FakeTeams, *steps: tuple) -> None:
    """Run ``_on_step`` on each step's infos (each step: one (stage, success) or None per team)."""
    for step in steps:
        callback.update_locals({"infos": teams.infos(*step)})
        assert callback.on_step() is True


def test_curriculum_starts_every_team_in_its_stage() -> None:
    """The stage is logged by FormationMetricsCallback (for the iteration it belongs to), not here."""
    _, teams, logger = driven(CurriculumCallback((4, 4, 4)))
    assert teams.calls == [("set_stage", (1,))] and logger.records == []
    resumed = CurriculumCallback((4, 4, 4))
    resumed.load_state_dict({"stage": 2, "iteration": 5, "stage_iteration": 1, "successes": []})
    _, teams, logger = driven(resumed)
    assert teams.calls == [("set_stage", (2,))] and teams.team_stages == [2, 2]  # resumes in the saved stage


def test_curriculum_advances_early_only_at_the_threshold_with_a_full_window(capsys: pytest.CaptureFixture[str]) -> None:
    callback, teams, _ = driven(CurriculumCallback((100, 100, 100), success_threshold=0.75, window=4, verbose=1))
    # three successes of stage 1: the rate is 1 but the window (4) is not full
    feed(callback, teams, ((1, True), (1, True)), ((1, True), None))
    callback.on_rollout_end()
    assert callback.stage == 1 and list(callback.successes) == [True, True, True]
    # episodes of other stages (e.g. ended by teams still placed for another stage) do not count
    feed(callback, teams, ((2, True), (3, True)), ((2, True), None))
    callback.on_rollout_end()
    assert callback.stage == 1 and len(callback.successes) == 3
    # a failure fills the window: 3 of 4 = 0.75 reaches the threshold, but only rollout ends advance the stage
    feed(callback, teams, ((1, False), None))
    assert callback.stage == 1 and teams.team_stages == [1, 1]
    callback.on_rollout_end()
    assert callback.stage == 2 and teams.team_stages == [2, 2] and teams.calls[-1] == ("set_stage", (2,))
    assert callback.iteration == 3 and callback.stage_iteration == 0 and len(callback.successes) == 0
    assert "stage 2" in capsys.readouterr().out
    # stage 2: a full window below the threshold (2 of 4) does not advance; the rolling rate rises to 3 of 4, which does
    feed(callback, teams, ((2, False), (2, False)), ((2, True), (2, True)))
    callback.on_rollout_end()
    assert callback.stage == 2 and list(callback.successes) == [False, False, True, True]
    feed(callback, teams, ((1, True), None))  # stage 1 again: ignored
    callback.on_rollout_end()
    assert callback.stage == 2
    feed(callback, teams, ((2, True), None))  # window now [False, True, True, True]
    callback.on_rollout_end()
    assert callback.stage == 3 and teams.team_stages == [3, 3] and callback.iteration == 6
    # stage 3 is the last: neither success nor iterations move it
    feed(callback, teams, *[((3, True), (3, True))] * 4)
    for _ in range(3):
        callback.on_rollout_end()
    assert callback.stage == 3 and teams.calls.count(("set_stage", (3,))) == 1


def test_curriculum_without_threshold_ignores_success() -> None:
    callback, teams, _ = driven(CurriculumCallback((3, 1, 1), window=2))
    for _ in range(2):
        feed(callback, teams, ((1, True), (1, True)))
        callback.on_rollout_end()
    assert callback.stage == 1
    callback.on_rollout_end()
    assert callback.stage == 2 and teams.team_stages == [2, 2]


def test_curriculum_iteration_count_wins_when_it_comes_first() -> None:
    callback, teams, _ = driven(CurriculumCallback((2, 2, 2), success_threshold=0.5, window=10))
    feed(callback, teams, ((1, True), (1, True)))  # rate 1, but only 2 of 10 episodes
    callback.on_rollout_end()
    assert callback.stage == 1
    callback.on_rollout_end()
    assert callback.stage == 2 and callback.iteration == 2


def test_curriculum_state_restores_the_rolling_window() -> None:
    """A callback restored from state_dict() continues exactly like the original."""
    original, teams, _ = driven(CurriculumCallback((100, 100, 100), success_threshold=1.0, window=3))
    feed(original, teams, ((1, True), (1, True)))
    original.on_rollout_end()
    restored = CurriculumCallback((100, 100, 100), success_threshold=1.0, window=3)
    restored.load_state_dict(json.loads(json.dumps(original.state_dict())))
    assert restored.state_dict() == {"stage": 1, "iteration": 1, "stage_iteration": 1, "successes": [True, True]}
    restored, restored_teams, _ = driven(restored)
    for callback, fake in ((original, teams), (restored, restored_teams)):
        feed(callback, fake, ((1, True), None))
        callback.on_rollout_end()
        assert callback.stage == 2 and callback.iteration == 2 and fake.team_stages == [2, 2]


@pytest.mark.parametrize(
    "kwargs",
    [
        {"iterations_per_stage": (1, 2)},
        {"iterations_per_stage": (1, 2, 3, 4)},
        {"iterations_per_stage": (1, -1, 3)},
        {"iterations_per_stage": (1, 1, 1), "success_threshold": -0.1},
        {"iterations_per_stage": (1, 1, 1), "success_threshold": 1.5},
    ],
)
def test_curriculum_rejects_invalid_arguments(kwargs: dict[str, Any]) -> None:
    with pytest.raises(ValueError, match=r"iterations_per_stage|success_threshold"):
        CurriculumCallback(**kwargs)


def test_curriculum_accepts_the_edges() -> None:
    assert CurriculumCallback((0, 0, 1), success_threshold=0.0).total_iterations == 1
    assert CurriculumCallback([5000, 5000, 15000], success_threshold=1.0).iterations_per_stage == (5000, 5000, 15000)


def test_curriculum_rejects_an_empty_window() -> None:
    with pytest.raises(ValueError, match="window"):
        CurriculumCallback((1, 1, 1), success_threshold=0.5, window=0)


def test_curriculum_skips_stages_of_zero_iterations() -> None:
    callback, teams, _ = driven(CurriculumCallback((0, 0, 3)))
    stages = []
    for _ in range(callback.total_iterations):
        stages.append(teams.team_stages[0])
        callback.on_rollout_end()
    assert stages == [3, 3, 3]


def test_curriculum_with_time_shares_ends_stages_at_their_share_of_the_budget(capsys: pytest.CaptureFixture[str]) -> None:
    clock = SimpleNamespace(budget=100.0, seconds=0.0)  # a clock whose time the test sets (seconds of a 100 s budget)
    callback, teams, _ = driven(CurriculumCallback((5000, 5000, None), time_shares=(0.2, 0.4), clock=clock, verbose=1))
    stages = []
    for seconds in (10.0, 19.9, 20.0, 39.9, 40.0, 99.0, 150.0):  # the clock at the end of successive iterations
        clock.seconds = seconds
        callback.on_rollout_end()
        stages.append(teams.team_stages[0])
    # stage 1 ends at the first iteration end at or past 20 s, stage 2 at the first past 40 s; the iterations
    # (5000 per stage) no longer count
    assert stages == [1, 1, 2, 2, 3, 3, 3] and callback.iteration == 7
    assert "its share of the time budget done" in capsys.readouterr().out
    # an iteration that ends past both shares skips stage 2; a resumed run whose clock is past them starts in stage 3
    clock.seconds = 0.0
    callback, teams, _ = driven(CurriculumCallback((1, 1, None), time_shares=(0.2, 0.4), clock=clock))
    clock.seconds = 41.0
    callback.on_rollout_end()
    assert teams.calls == [("set_stage", (1,)), ("set_stage", (2,)), ("set_stage", (3,))]
    resumed = CurriculumCallback((1, 1, None), time_shares=(0.2, 0.4), clock=clock)
    resumed.load_state_dict({"stage": 1, "iteration": 3, "stage_iteration": 3, "successes": []})
    _, teams, _ = driven(resumed)
    assert teams.team_stages == [3, 3]
    # shares of 0 skip stages 1 and 2 at once (a stage-3-only curriculum)
    clock.seconds = 0.0
    _, teams, _ = driven(CurriculumCallback((0, 0, None), time_shares=(0.0, 0.0), clock=clock))
    assert teams.team_stages == [3, 3]


@pytest.mark.parametrize(
    ("shares", "clock"),
    [
        ((0.2, 0.4), None),
        ((0.2, 0.4), SimpleNamespace(budget=None, seconds=0.0)),
        ((0.4, 0.2), SimpleNamespace(budget=10.0, seconds=0.0)),
        ((0.2, 1.5), SimpleNamespace(budget=10.0, seconds=0.0)),
        ((0.2,), SimpleNamespace(budget=10.0, seconds=0.0)),
    ],
)
def test_curriculum_rejects_time_shares_without_a_budget_or_out_of_order(shares: tuple, clock: Any) -> None:
    with pytest.raises(ValueError, match="time_shares must be two increasing fractions"):
        CurriculumCallback((1, 1, None), time_shares=shares, clock=clock)


# FormationMetricsCallback ---------------------------------------------------------------------------------------------


class EpisodeRecorder(BaseCallback):
    """Team-episodes measured from the per-step infos and dones (independently of the VecEnv's summaries)."""

    def __init__(self, n_agents: int) -> None:
        super().__init__()
        self.n_agents = n_agents
        self.running: dict[int, dict[str, Any]] = {}
        self.finished: list[dict[str, Any]] = []
        self.finished_at_rollout_end: list[list[dict[str, Any]]] = []

    def _on_step(self) -> bool:
        infos, dones = self.locals["infos"], self.locals["dones"]
        for team in range(len(infos) // self.n_agents):
            agents = infos[team * self.n_agents : (team + 1) * self.n_agents]
            run = self.running.setdefault(team, {"steps": 0, "errors": [], "collisions": np.zeros(2), "terms": []})
            run["steps"] += 1
            run["errors"].append(
                [
                    np.mean([info[key] for info in agents])
                    for key in ("angle_error_deg", "bearing_error", "neighbour_distance_error")
                ]
            )
            run["collisions"] += [
                sum(info["collisions_obstacle"] for info in agents),
                sum(info["collisions_agent"] for info in agents),
            ]
            run["terms"].append([np.mean([info[f"reward_{term}"] for info in agents]) for term in REWARD_TERMS])
            team_dones = dones[team * self.n_agents : (team + 1) * self.n_agents]
            assert team_dones.all() or not team_dones.any()  # a team ends as a whole
            if team_dones[0]:
                errors, terms = np.mean(run["errors"], axis=0), np.mean(run["terms"], axis=0)
                self.finished.append(
                    {
                        "formation/angle_error_deg": errors[0],
                        "formation/bearing_error": errors[1],
                        "formation/neighbour_distance_error": errors[2],
                        "episode/success_rate": float(agents[0]["success"]),
                        "episode/length": run["steps"],
                        "episode/collisions_obstacle": run["collisions"][0],
                        "episode/collisions_agent": run["collisions"][1] // 2,  # both agents of a pair report it
                        **{f"reward/{term}": value for term, value in zip(REWARD_TERMS, terms)},
                    }
                )
                del self.running[team]
        return True

    def _on_rollout_end(self) -> None:
        self.finished_at_rollout_end.append(list(self.finished))


METRIC_TAGS = EPISODE_SCALARS
HYPERPARAMETERS = {
    "recipe": "ch5-bearing",
    "n_steps": N_STEPS,
    "iterations": [3, 0, 0],
    "success_threshold": None,
    "ppo": {"learning_rate": 3e-4},
    "env": {"team_reward": True},
}
WINDOW = 3


@pytest.fixture(scope="module")
def metrics_run(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    """3 iterations of 8 steps, 2 teams, episodes of 5 steps (4 team-episodes per team), stage 2, logged to TensorBoard."""
    folder = tmp_path_factory.mktemp("metrics")
    model = tiny_ppo(n_envs=2, max_steps=5, stage=2)
    model.set_logger(configure(str(folder), ["tensorboard"]))
    recorder = EpisodeRecorder(N_AGENTS)
    learn_iterations(model, 3, [recorder, FormationMetricsCallback(HYPERPARAMETERS, window=WINDOW)])
    model.logger.close()
    return SimpleNamespace(
        recorder=recorder,
        events=read_events(folder),
        hparams=read_hparams(folder),
        steps=[N_STEPS * 2 * N_AGENTS * k for k in (1, 2, 3)],
    )


def test_metrics_are_written_for_every_iteration(metrics_run: SimpleNamespace) -> None:
    tags = metrics_run.events.Tags()["scalars"]
    for tag in [*METRIC_TAGS, "curriculum/stage"]:
        assert tag in tags, tag
        assert sorted(scalars(metrics_run.events, tag)) == metrics_run.steps, tag
    assert set(scalars(metrics_run.events, "curriculum/stage").values()) == {2.0}


def test_episode_length_matches_the_observed_episodes(metrics_run: SimpleNamespace) -> None:
    # 2 teams x 24 steps with episodes of max_steps = 5 steps: after iterations 1, 2, 3 (steps 8, 16, 24), 2, 6, 8 ended;
    # the goal is metres away and an agent moves 1.5 cm per step, so every episode is a time-out
    finished = metrics_run.recorder.finished_at_rollout_end
    assert [len(episodes) for episodes in finished] == [2, 6, 8]
    assert all(episode["episode/length"] == 5 for episode in finished[-1])
    assert all(episode["episode/success_rate"] == 0.0 for episode in finished[-1])
    assert list(scalars(metrics_run.events, "episode/length").values()) == [5.0, 5.0, 5.0]
    assert list(scalars(metrics_run.events, "episode/success_rate").values()) == [0.0, 0.0, 0.0]


def test_metrics_are_rolling_means_of_the_observed_episodes(metrics_run: SimpleNamespace) -> None:
    for step, episodes in zip(metrics_run.steps, metrics_run.recorder.finished_at_rollout_end):
        recent = episodes[-WINDOW:]
        for tag in METRIC_TAGS:
            expected = float(np.mean([episode[tag] for episode in recent]))
            assert scalars(metrics_run.events, tag)[step] == pytest.approx(expected, rel=1e-5, abs=1e-6), (tag, step)
    angle = list(scalars(metrics_run.events, "formation/angle_error_deg").values())
    assert all(value > 0 for value in angle)  # stage-2 starts are regular hexagons, but random actions bend them


def test_settings_go_to_the_hparams_tab_with_the_success_rate_and_errors_as_metrics(metrics_run: SimpleNamespace) -> None:
    """SB3's ``HParam``; nested settings flattened, lists as JSON, ``None`` left out (TensorBoard)."""
    assert metrics_run.hparams["metrics"] == list(HPARAM_METRICS)
    assert {"episode/success_rate", "formation/angle_error_deg", "formation/bearing_error"} <= set(HPARAM_METRICS)
    assert metrics_run.hparams["hparams"] == {
        "recipe": "ch5-bearing",
        "n_steps": float(N_STEPS),
        "iterations": "[3, 0, 0]",
        "ppo/learning_rate": 0.0003,
        "env/team_reward": 1.0,  # TensorBoard stores a bool as a number
    }
    assert hparam_values({"env": {"v_max": 0.05, "stage_disabled_terms": [["goal"], [], []]}}) == {
        "env/v_max": 0.05,
        "env/stage_disabled_terms": '[["goal"], [], []]',
    }


def test_custom_scalars_layout_is_written_and_names_written_charts(metrics_run: SimpleNamespace) -> None:
    events = metrics_run.events
    tags = [tag for tag in events.Tags()["tensors"] if "custom_scalars" in tag]
    assert len(tags) == 1
    layout = layout_pb2.Layout()
    layout.ParseFromString(events.Tensors(tags[0])[0].tensor_proto.string_val[0])
    expected = custom_scalars_layout()
    assert [category.title for category in layout.category] == list(expected)
    charted: set[str] = set()
    for category in layout.category:
        charts = {chart.title: list(chart.multiline.tag) for chart in category.chart}
        assert charts == {title: spec[1] for title, spec in expected[category.title].items()}
        for chart_tags in charts.values():
            charted.update(chart_tags)
    assert set(METRIC_TAGS) | {"curriculum/stage"} <= charted
    assert charted <= set(events.Tags()["scalars"])  # every chart shows a scalar the run wrote


def test_metrics_callback_logs_only_the_stage_before_any_episode_ends(tmp_path: Path) -> None:
    model = tiny_ppo(n_envs=1, max_steps=50)
    model.set_logger(configure(str(tmp_path), ["tensorboard"]))
    learn_iterations(model, 1, [FormationMetricsCallback()])
    model.logger.close()
    events = read_events(tmp_path)
    assert "curriculum/stage" in events.Tags()["scalars"]
    assert not set(METRIC_TAGS) & set(events.Tags()["scalars"])
    assert read_hparams(tmp_path) == {"metrics": list(HPARAM_METRICS), "hparams": {}}


# IterationProgressCallback --------------------------------------------------------------------------------------------------


def test_progress_bar_runs_through_a_short_learn(capsys: pytest.CaptureFixture[str]) -> None:
    model = tiny_ppo(n_envs=1, max_steps=5)
    curriculum = CurriculumCallback((1, 1, 1))
    bar = IterationProgressCallback(5, curriculum, initial_iteration=2)  # as when resuming after 2 of 5 iterations
    learn_iterations(model, 3, [curriculum, bar])
    err = capsys.readouterr().err
    assert "5/5" in err and "stage 3" in err and "agent-steps/s" in err and "success 0%" in err
    assert bar.bar.n == 5


class ThreadProbe(BaseCallback):
    """Records torch's thread count at every step; stops the rollout at step ``stop_at`` if given."""

    def __init__(self, stop_at: int | None = None) -> None:
        super().__init__()
        self.threads: list[int] = []
        self.stop_at = stop_at

    def _on_step(self) -> bool:
        self.threads.append(th.get_num_threads())
        return self.stop_at is None or len(self.threads) < self.stop_at


def test_collection_threads_hold_during_rollouts_only() -> None:
    previous = th.get_num_threads()
    th.set_num_threads(2)
    env = make_formation_vec_env("ch5-bearing", n_envs=2, seed=0, n_workers=2)
    try:
        model = PPO("MlpPolicy", env, n_steps=4, batch_size=24, n_epochs=1, seed=0, device="cpu")
        probe = ThreadProbe()
        model.learn(2 * 4 * env.num_envs, callback=[CollectionThreadsCallback(1), probe])
        assert probe.threads == [1] * 8 and th.get_num_threads() == 2  # training and afterwards: torch's own 2
        stopped = ThreadProbe(stop_at=3)
        model.learn(4 * env.num_envs, callback=[CollectionThreadsCallback(1), stopped])
        assert stopped.threads == [1, 1, 1] and th.get_num_threads() == 2  # a rollout stopped by a callback too
    finally:
        env.close()
        th.set_num_threads(previous)
