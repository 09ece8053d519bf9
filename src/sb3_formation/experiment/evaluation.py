"""Evaluating a policy on fixed-seed curriculum episodes (thesis 4.4, 5.4): success rate, errors and trajectories.

Episode k of an evaluation with seed s is played from ``FormationEnv.reset(seed=s + k)``, so every policy evaluated
with the same seed meets the same scenarios (start, goal, obstacles) whatever the number of teams or workers. The
policy is any :class:`~sb3_formation.controllers.base.TeamPolicy` (a trained model with its normaliser, a controller):
it gets the env's raw observations and decides itself what to do with them.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import json
import math
import os
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from sb3_formation.controllers.base import TeamPolicy
from sb3_formation.env.blocks import BlockStep, EngineBlocks
from sb3_formation.env.config import REWARD_TERMS, FormationConfig
from sb3_formation.env.geometry import ring_neighbours
from sb3_formation.env.state import TeamState
from sb3_formation.experiment.targets import default_protocol, evaluation_file, evaluation_folder, load_policy
from sb3_formation.sb3.callbacks import threads_beside_workers, torch_threads
from sb3_formation.sb3.metrics import EPISODE_METRICS
from sb3_formation.utils.files import atomic_write

#: Columns of ``episodes.csv``, in order (``reward_<term>``: the term's mean per step and agent).
EPISODE_COLUMNS = (
    "episode",
    "seed",
    "team",
    "stage",
    "success",
    "return",
    *EPISODE_METRICS,
    "final_goal_distance",
    *(f"reward_{term}" for term in REWARD_TERMS),
)
#: Per-step, per-agent arrays of :class:`Trajectories` -> where a step's arrays hold them: a column of the info values
#: or of the contacts
STEP_RECORDS = {
    "angle_error_deg": ("info_values", 0),
    "bearing_error": ("info_values", 1),
    "neighbour_distance_error": ("info_values", 2),
    "collisions_obstacle": ("contacts", 1),
    "collisions_agent": ("contacts", 0),
}
SUMMARY_FILE, EPISODES_FILE, TRAJECTORIES_FILE = "summary.json", "episodes.csv", "trajectories.npz"
#: Teams an evaluation plays at once by default: the policy then acts for 16 teams per call, which took 0.88x the
#: time of 8 teams for the shipped ch5-bearing policy (``benchmarks/evaluation_throughput.py``, 2026-11-25)
EVALUATION_TEAMS = 16


def wilson_interval(successes: int, trials: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson score interval of a success rate (95 % for the default z).

    :param successes: number of successes
    :param trials: number of trials (> 0)
    :param z: standard-normal quantile of the confidence level
    """
    if trials <= 0 or not 0 <= successes <= trials:
        raise ValueError(f"need 0 <= successes <= trials and trials > 0, got {successes} of {trials}")
    rate = successes / trials
    denominator = 1 + z * z / trials
    centre = (rate + z * z / (2 * trials)) / denominator
    half_width = z * math.sqrt(rate * (1 - rate) / trials + z * z / (4 * trials * trials)) / denominator
    low = 0.0 if successes == 0 else max(0.0, centre - half_width)  # exact ends: no rounding residue at 0 or n
    high = 1.0 if successes == trials else min(1.0, centre + half_width)
    return low, high


@dataclass
class Trajectories:
    """Step-by-step records of evaluation episodes, padded with NaN after each episode's end.

    Row 0 of the per-step arrays is the state after ``reset``; row t (1 <= t <= ``lengths[k]``) is the state after
    step t. Errors, collisions and actions have no value in row 0 (NaN). Error columns are those of the agents' step
    infos: ``angle_error_deg`` = abs(beta_ref - beta^i) (deg), ``bearing_error`` = half the sum of norm(g_ref - g) over
    the two neighbours, ``neighbour_distance_error`` = half the sum of max(d_j^i - d_ref, 0) (m), collisions = contacts
    of the agent that step.

    :param config: task configuration of the episodes
    :param episodes: ``(K,)`` evaluation episode indices
    :param seeds: ``(K,)`` reset seeds
    :param lengths: ``(K,)`` steps played
    :param success: ``(K,)`` whether the centroid reached the goal
    :param goals: ``(K, 2)`` goal positions (m)
    :param obstacles: ``(K, M, 3)`` obstacle x, y, radius (m), NaN rows when an episode has fewer
    :param positions: ``(K, T + 1, n, 2)`` agent positions (m)
    :param velocities: ``(K, T + 1, n, 2)`` agent velocities (m/s)
    :param actions: ``(K, T + 1, n, 2)`` actions applied in the step that led to the row (clipped to [-1, 1])
    :param angle_error_deg: ``(K, T + 1, n)``
    :param bearing_error: ``(K, T + 1, n)``
    :param neighbour_distance_error: ``(K, T + 1, n)``
    :param collisions_obstacle: ``(K, T + 1, n)``
    :param collisions_agent: ``(K, T + 1, n)`` (each touching pair counted by both agents)
    :param goal_distance: ``(K, T + 1)`` centroid-goal distance (m)
    """

    config: FormationConfig
    episodes: np.ndarray
    seeds: np.ndarray
    lengths: np.ndarray
    success: np.ndarray
    goals: np.ndarray
    obstacles: np.ndarray
    positions: np.ndarray
    velocities: np.ndarray
    actions: np.ndarray
    angle_error_deg: np.ndarray
    bearing_error: np.ndarray
    neighbour_distance_error: np.ndarray
    collisions_obstacle: np.ndarray
    collisions_agent: np.ndarray
    goal_distance: np.ndarray

    def __len__(self) -> int:
        return len(self.episodes)

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write every array (and the configuration as JSON) to an ``.npz`` file, atomically."""
        path = Path(path)
        arrays = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "config"}
        arrays["config_json"] = np.array(json.dumps(dataclasses.asdict(self.config)))
        buffer = io.BytesIO()
        np.savez_compressed(buffer, **arrays)
        atomic_write(path, buffer.getvalue())

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Trajectories:
        """Read a file written by :meth:`save`."""
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"no trajectories at {path}: run `sb3-formation evaluate` first")
        try:
            with np.load(path, allow_pickle=False) as data:
                arrays = {key: data[key] for key in data.files}
            config = FormationConfig(**json.loads(str(arrays.pop("config_json"))))
            return cls(config=config, **arrays)
        except (KeyError, TypeError, ValueError, OSError, zipfile.BadZipFile) as error:
            raise ValueError(f"{path} is not a trajectories file written by sb3-formation: {error}") from error

    def steps(self, index: int) -> dict[str, np.ndarray]:
        """The per-step arrays of the ``index``-th recorded episode without padding (``lengths[index] + 1`` rows)."""
        rows = int(self.lengths[index]) + 1
        names = (*STEP_RECORDS, "positions", "velocities", "actions", "goal_distance")
        return {name: getattr(self, name)[index, :rows] for name in names}

    def team_state(self, index: int, step: int) -> TeamState:
        """The recorded team's state after ``step`` of the ``index``-th recorded episode (no lidar readings), e.g. to
        draw it with :func:`~sb3_formation.env.rendering.render_frame` without replaying the policy."""
        if not 0 <= step <= int(self.lengths[index]):
            raise IndexError(f"step {step} is outside episode {int(self.episodes[index])}'s 0 to {int(self.lengths[index])}")
        obstacles = self.obstacles[index]
        zeros = np.zeros(self.config.n_agents, dtype=np.int64)
        counts = {
            name: np.nan_to_num(getattr(self, name)[index, step]).astype(np.int64)
            for name in ("collisions_agent", "collisions_obstacle")
        }
        return TeamState(
            step=step,
            positions=self.positions[index, step],
            velocities=self.velocities[index, step],
            goal=self.goals[index],
            obstacles=obstacles[~np.isnan(obstacles).any(axis=1)],
            neighbours=ring_neighbours(self.config.n_agents),
            contacts_agent=counts["collisions_agent"] if step else zeros,
            contacts_obstacle=counts["collisions_obstacle"] if step else zeros,
            angle_errors_deg=self.angle_error_deg[index, step],
            bearing_errors=self.bearing_error[index, step],
            neighbour_distance_errors=self.neighbour_distance_error[index, step],
            centroid=self.positions[index, step].mean(axis=0),
            goal_distance=float(self.goal_distance[index, step]),
        )


class _Recorder:
    """Collects one episode's per-step records for :class:`Trajectories`: the state after the reset, then each step's
    arrays."""

    def __init__(self, state: TeamState) -> None:
        n_agents = state.n_agents
        nan = np.full(n_agents, np.nan)
        self.goal, self.obstacles = state.goal, state.obstacles
        self.rows: dict[str, list[np.ndarray]] = {name: [nan] for name in STEP_RECORDS}
        self.rows["positions"] = [state.positions]
        self.rows["velocities"] = [state.velocities]
        self.rows["actions"] = [np.full((n_agents, 2), np.nan)]
        self.rows["goal_distance"] = [np.array(state.goal_distance)]

    def add(self, step: BlockStep, slots: slice, actions: np.ndarray) -> None:
        """Add a step: the team's ``slots`` of the step's arrays, and the actions the policy gave."""
        for name, (array, column) in STEP_RECORDS.items():
            self.rows[name].append(getattr(step, array)[slots, column].astype(np.float64))
        self.rows["positions"].append(step.positions[slots].copy())
        self.rows["velocities"].append(step.velocities[slots].copy())
        self.rows["actions"].append(np.clip(actions[slots], -1.0, 1.0).astype(np.float64))
        self.rows["goal_distance"].append(np.array(step.info_values[slots.start, 4]))


@dataclass
class PlayJob:
    """Episodes to play, and the policy that acts in them.

    :param policy: the policy, already fitted to ``config``
    :param config: task configuration of the episodes
    :param seed: episode k is played from ``reset(seed=seed + k)``
    :param episodes: the episode indices to play
    :param n_teams: teams played at once
    :param deterministic: ask the policy for its noise-free actions
    :param record: record every step of the episodes with an index below this
    :param n_workers: processes stepping the teams, this one included
    """

    policy: TeamPolicy
    config: FormationConfig
    seed: int
    episodes: list[int]
    n_teams: int
    deterministic: bool
    record: int
    n_workers: int = 1


def play_episodes(
    job: PlayJob,
    on_episode: Callable[[], None] | None = None,
    on_step: Callable[[TeamState, int], None] | None = None,
) -> tuple[list[dict[str, Any]], list[tuple[int, _Recorder, bool]]]:
    """Play ``job.episodes`` on ``job.n_teams`` teams; a team that ends an episode starts the next one left (teams in
    order), and a team left without one is no longer stepped.

    This is the package's one episode loop: evaluation, videos and ``sb3-formation rollout`` all play through it. The
    teams are stepped by :class:`~sb3_formation.env.blocks.EngineBlocks` without automatic resets; the policy sees
    every team's observations in one batch (a team without an episode keeps its last ones).

    :param on_episode: called after each episode
    :param on_step: called with (team state, episode) after each reset and each step (every team in this process:
        ``n_workers`` must be 1)
    :return: one row per episode (in the order they ended), and (episode, recorder, success) of recorded episodes
    """
    config, n_agents, n_teams = job.config, job.config.n_agents, job.n_teams
    if on_step is not None and job.n_workers > 1:
        raise ValueError("on_step reads every team in this process: play with n_workers=1")
    blocks = EngineBlocks([config] * n_teams, job.n_workers, auto_reset=False)
    queue = list(reversed(job.episodes))
    current: list[int | None] = [None] * n_teams
    recorders: list[_Recorder | None] = [None] * n_teams
    observations = np.zeros((n_teams * n_agents, blocks.local.engine.observation_dim), np.float32)
    episode_starts = np.ones(n_teams * n_agents, dtype=bool)
    rows: list[dict[str, Any]] = []
    recorded: list[tuple[int, _Recorder, bool]] = []

    def slots(team: int) -> slice:
        return slice(team * n_agents, (team + 1) * n_agents)

    def start(teams: list[int]) -> None:
        """Give each of ``teams`` the next episode left, in order, and reset them."""
        for team in teams:
            current[team] = queue.pop() if queue else None
        started = [team for team in teams if current[team] is not None]
        if not started:
            return
        reset = blocks.reset(started, [job.seed + current[team] for team in started], [None] * len(started))
        watched = started if on_step is not None else [team for team in started if current[team] < job.record]
        states = blocks.call_teams("team_states", watched) if watched else {}
        for team in started:
            observations[slots(team)] = reset[team]
            episode_starts[slots(team)] = True
            recorders[team] = _Recorder(states[team]) if current[team] < job.record else None
            if on_step is not None:
                on_step(states[team], current[team])

    try:
        start(list(range(n_teams)))
        states = None
        while any(episode is not None for episode in current):
            playing = [team for team, episode in enumerate(current) if episode is not None]
            actions, states = job.policy.predict(
                observations, state=states, episode_start=episode_starts, deterministic=job.deterministic
            )
            actions = blocks.checked_actions(np.asarray(actions).reshape(n_teams * n_agents, 2), playing)
            episode_starts[:] = False
            step = blocks.step(actions)
            for team in playing:
                if recorders[team] is not None:
                    recorders[team].add(step, slots(team), actions)
                if on_step is not None:
                    on_step(blocks.local.engine.team_state(team), current[team])
            ended = {episode.team: episode for episode in step.episodes}
            for team in playing:
                if team not in ended:
                    observations[slots(team)] = step.observations[slots(team)]
                    continue
                episode = ended[team]
                summary = dict(episode.summary)
                terms = summary.pop("reward_terms")
                rows.append(
                    {
                        "episode": current[team],
                        "seed": job.seed + current[team],
                        "team": team,
                        **summary,
                        "comm_exceeded_fraction": episode.comm_exceeded_steps / summary["length"],
                        "final_goal_distance": float(step.info_values[episode.first_slot, 4]),
                        **{f"reward_{name}": value for name, value in terms.items()},
                    }
                )
                if recorders[team] is not None:
                    recorded.append((current[team], recorders[team], episode.success))
                if on_episode is not None:
                    on_episode()
            start(sorted(ended))
    finally:
        blocks.close()
    return rows, recorded


def _stack(config: FormationConfig, seed: int, recorded: list[tuple[int, _Recorder, bool]]) -> Trajectories | None:
    """Pad the recorded episodes (of an evaluation with ``seed``) to one length and stack them, in episode order."""
    if not recorded:
        return None
    recorded = sorted(recorded, key=lambda item: item[0])
    lengths = np.array([len(recorder.rows["positions"]) - 1 for _, recorder, _ in recorded], dtype=np.int64)
    rows = int(lengths.max()) + 1
    arrays: dict[str, np.ndarray] = {}
    for name in recorded[0][1].rows:
        padded = []
        for _, recorder, _ in recorded:
            values = np.stack(recorder.rows[name]).astype(np.float64)
            pad = np.full((rows - len(values), *values.shape[1:]), np.nan)
            padded.append(np.concatenate([values, pad]))
        arrays[name] = np.stack(padded)
    most_obstacles = max(len(recorder.obstacles) for _, recorder, _ in recorded)
    obstacles = np.full((len(recorded), most_obstacles, 3), np.nan)
    for index, (_, recorder, _) in enumerate(recorded):
        obstacles[index, : len(recorder.obstacles)] = recorder.obstacles
    episodes = np.array([episode for episode, _, _ in recorded], dtype=np.int64)
    return Trajectories(
        config=config,
        episodes=episodes,
        seeds=episodes + seed,
        lengths=lengths,
        success=np.array([success for _, _, success in recorded], dtype=bool),
        goals=np.stack([recorder.goal for _, recorder, _ in recorded]).astype(np.float64),
        obstacles=obstacles,
        **arrays,
    )


def seed_policy(policy: TeamPolicy, seed: int) -> None:
    """Seed what a policy samples from: torch's generator (SB3 policies sample with it) and the policy's own ``seed``."""
    torch.manual_seed(seed)
    if hasattr(policy, "seed"):
        policy.seed(seed)


@dataclass
class EvaluationResult:
    """Outcome of :func:`evaluate`.

    :param episodes: one row per episode, in episode order (the columns of :data:`EPISODE_COLUMNS`)
    :param trajectories: step-by-step records of the first episodes (``None`` if none were recorded)
    :param stage: curriculum stage of the episodes
    :param seed: episode k was played from ``reset(seed=seed + k)``
    :param deterministic: whether the policy's mean actions were used
    :param model: where the model came from (``file`` and ``sha256``), if known
    """

    episodes: list[dict[str, Any]]
    trajectories: Trajectories | None
    stage: int
    seed: int
    deterministic: bool
    n_agents: int
    model: dict[str, str] | None = None
    summary: dict[str, Any] = field(init=False)

    def __post_init__(self) -> None:
        successes = [episode for episode in self.episodes if episode["success"]]
        low, high = wilson_interval(len(successes), len(self.episodes))
        self.summary = {
            "episodes": len(self.episodes),
            "successes": len(successes),
            "success_rate": len(successes) / len(self.episodes),
            "success_rate_ci95": [low, high],
            "stage": self.stage,
            "seed": self.seed,
            "deterministic": self.deterministic,
            "n_agents": self.n_agents,
            "model": self.model,
            "successful_episodes": _mean_and_std(successes),
            "all_episodes": _mean_and_std(self.episodes),
        }

    def save(self, folder: str | os.PathLike[str]) -> dict[str, Path]:
        """Write ``summary.json``, ``episodes.csv`` and (if recorded) ``trajectories.npz`` into ``folder``, atomically.

        :return: the files written, by kind
        """
        folder = Path(folder)
        files = {"summary": folder / SUMMARY_FILE, "episodes": folder / EPISODES_FILE}
        atomic_write(files["summary"], json.dumps(self.summary, indent=2))
        table = io.StringIO()
        writer = csv.DictWriter(table, fieldnames=EPISODE_COLUMNS, lineterminator="\n")
        writer.writeheader()
        writer.writerows(self.episodes)
        atomic_write(files["episodes"], table.getvalue())
        if self.trajectories is not None:
            files["trajectories"] = folder / TRAJECTORIES_FILE
            self.trajectories.save(files["trajectories"])
        else:  # no trajectories from an earlier evaluation may stay beside this one's summary
            (folder / TRAJECTORIES_FILE).unlink(missing_ok=True)
        return files


def _mean_and_std(episodes: list[dict[str, Any]]) -> dict[str, dict[str, float | None]]:
    """Mean and population std of each of :data:`EPISODE_METRICS` over ``episodes`` (``None`` when there are none)."""
    return {
        name: {
            "mean": float(np.mean([episode[name] for episode in episodes])) if episodes else None,
            "std": float(np.std([episode[name] for episode in episodes])) if episodes else None,
        }
        for name in EPISODE_METRICS
    }


def model_fingerprint(path: str | os.PathLike[str]) -> dict[str, str]:
    """The file and SHA-256 of a saved model, to tell whether a stored evaluation is of the same model."""
    digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    return {"file": str(path), "sha256": digest}


def policy_identity(policy: TeamPolicy) -> dict[str, Any] | None:
    """What an evaluation summary records of its policy: a model file with its SHA-256, or a controller with its gains
    (``None`` for anything else)."""
    source = getattr(policy, "source", None)
    if source is not None:
        return model_fingerprint(source)
    gains = getattr(policy, "gains", None)
    return None if gains is None else {"controller": type(policy).__name__, "gains": gains}


def evaluate(
    policy: TeamPolicy,
    episodes: int,
    stage: int = 3,
    seed: int = 0,
    n_envs: int = EVALUATION_TEAMS,
    deterministic: bool = True,
    env_overrides: dict[str, Any] | None = None,
    n_workers: int = 1,
    record: int = 5,
    progress_bar: bool = False,
) -> EvaluationResult:
    """Play ``episodes`` episodes of ``stage`` with a policy; episode k starts from ``reset(seed=seed + k)``.

    The episodes are spread over ``n_envs`` teams whose observations go through the policy in one batch; with
    ``n_workers`` > 1, worker processes step shares of the teams while this process steps the first share and runs the
    policy. The scenarios depend only on ``seed``; the same (seed, n_envs) gives bit-identical results, whatever
    ``n_workers``.

    :param policy: the policy (a :class:`~sb3_formation.sb3.trained.TrainedPolicy`, a controller, ...)
    :param episodes: number of episodes
    :param stage: curriculum stage of the scenarios (3 in the thesis's evaluations)
    :param seed: seed of the scenarios
    :param n_envs: teams played at once (over all workers)
    :param deterministic: use the policy's mean action (else sample; the sampling is seeded from ``seed``)
    :param env_overrides: :class:`FormationConfig` fields to change from the policy's configuration
    :param n_workers: processes playing the episodes
    :param record: record the step-by-step trajectories of the first ``record`` episodes
    :param progress_bar: show a tqdm progress bar of the episodes played
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if not 1 <= n_workers <= n_envs:
        raise ValueError(f"n_workers must be in [1, n_envs={n_envs}], got {n_workers}")
    if record < 0:
        raise ValueError(f"record must be >= 0, got {record}")
    config = policy.config.replace(**{**(env_overrides or {}), "stage": stage})
    policy = policy.fit(config)
    n_teams = min(n_envs, episodes)
    job = PlayJob(policy, config, seed, list(range(episodes)), n_teams, deterministic, record, min(n_workers, n_teams))
    with (
        tqdm(total=episodes, desc="evaluating", unit="episode", disable=not progress_bar) as bar,
        torch.random.fork_rng(),
        torch_threads(threads_beside_workers(job.n_workers)),
    ):
        seed_policy(policy, seed)
        rows, recorded = play_episodes(job, on_episode=lambda: bar.update(1))
    trajectories = _stack(config, seed, recorded)
    return EvaluationResult(
        episodes=sorted(rows, key=lambda row: row["episode"]),
        trajectories=trajectories,
        stage=stage,
        seed=seed,
        deterministic=deterministic,
        n_agents=config.n_agents,
        model=policy_identity(policy),
    )


#: Columns of :func:`comparison_table` after the success rate.
TABLE_METRICS = {name: metric for name, metric in EPISODE_METRICS.items() if metric.in_table}


def comparison_table(summaries: dict[str, dict[str, Any]], over: str = "successful") -> str:
    """A Markdown table of evaluation summaries: success rate with its 95 % interval, then mean ± std of each metric.

    :param summaries: policy label -> :attr:`EvaluationResult.summary`
    :param over: ``"successful"`` (the thesis's choice) or ``"all"`` episodes for the means
    """
    if over not in ("successful", "all"):
        raise ValueError(f"over must be 'successful' or 'all', got {over!r}")
    headings = ["policy", "episodes", "success rate (95 % CI)", *(metric.label for metric in TABLE_METRICS.values())]
    lines = ["| " + " | ".join(headings) + " |", "|" + "|".join(["---"] + ["---:"] * (len(headings) - 1)) + "|"]
    for label, summary in summaries.items():
        low, high = summary["success_rate_ci95"]
        cells = [label, str(summary["episodes"]), f"{summary['success_rate']:.1%} ({low:.1%} - {high:.1%})"]
        for name in TABLE_METRICS:
            statistics = summary[f"{over}_episodes"][name]
            cells.append(
                "-"
                if statistics["mean"] is None
                else f"{table_number(statistics['mean'])} ± {table_number(statistics['std'])}"
            )
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def table_number(value: float) -> str:
    """A table number: whole from 100, one decimal from 10, three significant digits below."""
    if abs(value) >= 100:
        return f"{value:.0f}"
    return f"{value:.1f}" if abs(value) >= 10 else f"{value:.3g}"


def evaluate_target(
    target: str | os.PathLike[str],
    protocol: dict[str, Any] | None = None,
    preset: str | None = None,
    device: str = "auto",
    progress_bar: bool = False,
    out: str | os.PathLike[str] | None = None,
) -> EvaluationResult:
    """Evaluate the policy a target names (see :func:`~sb3_formation.experiment.targets.load_policy`) and write its files.

    :param target: a run folder, a model ``.zip`` or ``controller:<name>``
    :param protocol: :func:`evaluate` arguments (``episodes``, ``stage``, ``seed``, ``n_envs``, ``workers``,
        ``deterministic``, ``record``, ``env_overrides``); ``episodes`` and ``stage`` default to the evaluation protocol
        of the target's set-up (the thesis's: stage 3, 500 episodes in chapter 4, 200 in chapter 5)
    :param preset: the set-up of a ``controller:`` target
    :param device: torch device
    :param progress_bar: show a progress bar
    :param out: folder for the files (default: :func:`~sb3_formation.experiment.targets.evaluation_folder`)
    """
    protocol = {key: value for key, value in (protocol or {}).items() if value is not None}
    policy = load_policy(target, preset=preset, device=device)
    protocol = {**default_protocol(target, preset), **protocol}
    if "episodes" not in protocol:
        raise ValueError(f"{target} belongs to no run folder whose set-up gives the number of episodes: give --episodes")
    if "workers" in protocol:
        protocol["n_workers"] = protocol.pop("workers")
    result = evaluate(policy, progress_bar=progress_bar, **protocol)
    result.save(out or evaluation_folder(target, preset))
    return result


def load_summary(target: str | os.PathLike[str], preset: str | None = None) -> dict[str, Any]:
    """The stored evaluation summary of a target (see :func:`~sb3_formation.experiment.targets.evaluation_file`).

    :raises FileNotFoundError: none was written
    :raises ValueError: the file is not an evaluation summary
    """
    path = evaluation_file(target, SUMMARY_FILE, preset)
    try:
        summary = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path} is not valid JSON: {error}") from error
    if not isinstance(summary, dict) or "success_rate" not in summary:
        raise ValueError(f"{path} is not an evaluation summary written by sb3-formation")
    return summary


def stored_summary(target: str | os.PathLike[str], protocol: dict[str, Any], preset: str | None = None) -> dict | None:
    """The target's stored evaluation summary if it is of the same policy (the model file's SHA-256, or the controller
    and its gains) under ``protocol`` (summary keys such as ``episodes``, ``stage``, ``seed``), else ``None``."""
    try:
        summary = load_summary(target, preset)
        identity = policy_identity(load_policy(target, preset, device="cpu"))
    except (FileNotFoundError, ValueError):
        return None
    same_policy = identity is not None and summary.get("model") == identity
    return summary if same_policy and all(summary.get(key) == value for key, value in protocol.items()) else None
