"""Evaluating a policy on fixed-seed curriculum episodes (thesis 4.4, 5.4): success rate, errors and trajectories.

Episode k of an evaluation with seed s is played from ``FormationEnv.reset(seed=s + k)``, so every policy evaluated
with the same seed meets the same scenarios (start, goal, obstacles) whatever the number of teams or workers. The
policy is anything with Stable-Baselines3's ``predict(observation, state, episode_start, deterministic)``; its
observations are scaled with frozen normaliser statistics, as in training.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import json
import math
import multiprocessing
import os
import traceback
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cloudpickle
import numpy as np
import torch
from tqdm.auto import tqdm

from sb3_formation.env.config import REWARD_TERMS, FormationConfig
from sb3_formation.env.episodes import EpisodeStatistics
from sb3_formation.env.formation_env import FormationEnv
from sb3_formation.experiment.training import TrainedModel, load_trained
from sb3_formation.sb3.normalization import STATE_KEYS, observation_scale, scale_observations
from sb3_formation.sb3.vec_env import slot_observations
from sb3_formation.utils.files import atomic_write

#: Thesis evaluation sizes: 500 episodes in chapter 4 (thesis 4.4), 200 in chapter 5 (thesis 5.4), by layout.
THESIS_EVALUATION_EPISODES = {"ch4": 500, "ch5": 200}
#: Per-episode metrics summarised with mean and std over successful episodes and over all episodes.
EPISODE_METRICS = (
    "angle_error_deg",
    "bearing_error",
    "neighbour_distance_error",
    "length",
    "collisions_obstacle",
    "collisions_agent",
    "comm_exceeded_fraction",
)
#: Columns of ``episodes.csv``, in order (``reward_<term>``: the term's mean per step and agent).
EPISODE_COLUMNS = (
    "episode",
    "seed",
    "team",
    "stage",
    "success",
    "length",
    "return",
    "angle_error_deg",
    "bearing_error",
    "neighbour_distance_error",
    "collisions_obstacle",
    "collisions_agent",
    "comm_exceeded_fraction",
    "final_goal_distance",
    *(f"reward_{term}" for term in REWARD_TERMS),
)
#: Per-step, per-agent arrays of :class:`Trajectories`, read from the agents' step infos.
STEP_ERRORS = ("angle_error_deg", "bearing_error", "neighbour_distance_error", "collisions_obstacle", "collisions_agent")
SUMMARY_FILE, EPISODES_FILE, TRAJECTORIES_FILE = "summary.json", "episodes.csv", "trajectories.npz"


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
        names = (*STEP_ERRORS, "positions", "velocities", "actions", "goal_distance")
        return {name: getattr(self, name)[index, :rows] for name in names}


class _Recorder:
    """Collects one episode's per-step records for :class:`Trajectories`."""

    def __init__(self, env: FormationEnv) -> None:
        n_agents = env.config.n_agents
        nan = np.full(n_agents, np.nan)
        self.goal, self.obstacles = env.goal.copy(), np.asarray(env.obstacles, dtype=np.float64).reshape(-1, 3)
        self.rows: dict[str, list[np.ndarray]] = {name: [nan] for name in STEP_ERRORS}
        self.rows["positions"] = [env.world.positions.copy()]
        self.rows["velocities"] = [env.world.velocities.copy()]
        self.rows["actions"] = [np.full((n_agents, 2), np.nan)]
        self.rows["goal_distance"] = [np.array(env.goal_distance)]

    def add(self, env: FormationEnv, actions: np.ndarray, infos: list[dict[str, Any]]) -> None:
        for name in STEP_ERRORS:
            self.rows[name].append(np.array([info[name] for info in infos], dtype=np.float64))
        self.rows["positions"].append(env.world.positions.copy())
        self.rows["velocities"].append(env.world.velocities.copy())
        self.rows["actions"].append(np.clip(actions, -1.0, 1.0).astype(np.float64))
        self.rows["goal_distance"].append(np.array(env.goal_distance))


@dataclass
class PlayJob:
    """What one process plays: its episodes, and everything needed to act in them (picklable)."""

    agent: Any
    config: FormationConfig
    normalizer_state: dict[str, np.ndarray]
    team_observations: bool
    seed: int
    episodes: list[int]
    n_teams: int
    deterministic: bool
    record: int
    first_team: int = 0  #: global index of this job's first team (episode rows name global teams)


def play_episodes(
    job: PlayJob,
    on_episode: Callable[[], None] | None = None,
    on_step: Callable[[FormationEnv, int, list[dict[str, Any]] | None], None] | None = None,
) -> tuple[list[dict[str, Any]], list[tuple[int, _Recorder, bool]]]:
    """Play ``job.episodes`` on ``job.n_teams`` teams; a team that ends an episode starts the next one left.

    :param on_episode: called after each episode
    :param on_step: called with (env, episode, infos) after each reset (infos ``None``) and each step
    :return: one row per episode (in the order they ended), and (episode, recorder, success) of recorded episodes
    """
    config, n_agents = job.config, job.config.n_agents
    scale = observation_scale(job.normalizer_state)
    clip = float(job.normalizer_state["clip_obs"])
    clip_obs = None if math.isnan(clip) else clip
    envs = [FormationEnv(config, render_mode="rgb_array" if on_step else None) for _ in range(job.n_teams)]
    queue = list(reversed(job.episodes))
    current: list[int | None] = [None] * job.n_teams
    statistics = [EpisodeStatistics() for _ in envs]
    comm_exceeded = [0] * job.n_teams
    recorders: list[_Recorder | None] = [None] * job.n_teams
    episode_starts = np.ones(job.n_teams * n_agents, dtype=bool)
    rows: list[dict[str, Any]] = []
    recorded: list[tuple[int, _Recorder, bool]] = []

    def start(team: int) -> np.ndarray | None:
        if not queue:
            current[team] = None
            return None
        episode = current[team] = queue.pop()
        env = envs[team]
        team_observation, _ = env.reset(seed=job.seed + episode)
        statistics[team].reset()
        comm_exceeded[team] = 0
        recorders[team] = _Recorder(env) if episode < job.record else None
        if on_step is not None:
            on_step(env, episode, None)
        return slot_observations(np.stack(list(team_observation.values())), job.team_observations)

    first = [start(team) for team in range(job.n_teams)]
    width = next(o for o in first if o is not None).shape[1]
    # a team left without an episode (more teams than episodes) holds zeros and is never stepped
    observations = np.concatenate([np.zeros((n_agents, width), np.float32) if o is None else o for o in first])
    states = None
    while any(episode is not None for episode in current):
        actions, states = job.agent.predict(
            scale_observations(observations, scale, clip_obs),
            state=states,
            episode_start=episode_starts,
            deterministic=job.deterministic,
        )
        actions = np.asarray(actions).reshape(job.n_teams * n_agents, 2)
        episode_starts[:] = False
        for team, episode in enumerate(current):
            if episode is None:
                continue
            env, block = envs[team], slice(team * n_agents, (team + 1) * n_agents)
            team_observations, rewards, terminated, truncated, infos = env.step_array(actions[block])
            statistics[team].add(rewards, infos)
            comm_exceeded[team] += bool((env.formation.neighbour_distances > config.d_comm).any())
            if recorders[team] is not None:
                recorders[team].add(env, actions[block], infos)
            if on_step is not None:
                on_step(env, episode, infos)
            if not (terminated or truncated):
                observations[block] = slot_observations(team_observations, job.team_observations)
                continue
            summary = statistics[team].summary(success=terminated, stage=env.stage)
            terms = summary.pop("reward_terms")
            rows.append(
                {
                    "episode": episode,
                    "seed": job.seed + episode,
                    "team": job.first_team + team,
                    **summary,
                    "comm_exceeded_fraction": comm_exceeded[team] / summary["length"],
                    "final_goal_distance": env.goal_distance,
                    **{f"reward_{name}": value for name, value in terms.items()},
                }
            )
            if recorders[team] is not None:
                recorded.append((episode, recorders[team], terminated))
            if on_episode is not None:
                on_episode()
            following = start(team)
            if following is not None:
                observations[block] = following
                episode_starts[block] = True
    for env in envs:
        env.close()
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


def _worker(index: int, job: bytes, progress: Any) -> None:  # pragma: no cover - runs in a subprocess
    """Play a pickled :class:`PlayJob`; put (index, "episode", None) per episode, then (index, "done", result) or
    (index, "error", text)."""
    try:
        play_job: PlayJob = cloudpickle.loads(job)
        torch.set_num_threads(1)
        torch.manual_seed(play_job.seed + play_job.episodes[0])
        result = play_episodes(play_job, on_episode=lambda: progress.put((index, "episode", None)))
        progress.put((index, "done", result))
    except BaseException as error:  # report to the parent, which raises it
        progress.put((index, "error", f"{type(error).__name__}: {error}\n{traceback.format_exc()}"))


def _play_in_workers(jobs: list[PlayJob], on_episode: Callable[[], None]) -> tuple[list, list]:
    """Play each job in its own process (``forkserver`` where available); gather rows and recordings."""
    method = "forkserver" if "forkserver" in multiprocessing.get_all_start_methods() else "spawn"
    context = multiprocessing.get_context(method)
    progress = context.Queue()
    processes = [
        context.Process(target=_worker, args=(index, cloudpickle.dumps(job), progress), daemon=True)
        for index, job in enumerate(jobs)
    ]
    for process in processes:
        process.start()
    rows: list[dict[str, Any]] = []
    recorded: list = []
    reported: set[int] = set()
    try:
        while len(reported) < len(processes):
            try:
                worker, kind, payload = progress.get(timeout=5)
            except Exception:  # queue.Empty: check that the workers that have not reported are still there
                silent = [index for index, process in enumerate(processes) if index not in reported and not process.is_alive()]
                if silent:
                    process = processes[silent[0]]
                    raise RuntimeError(f"evaluation worker (pid {process.pid}) died, exit code {process.exitcode}") from None
                continue
            if kind == "episode":
                on_episode()
            elif kind == "done":
                rows.extend(payload[0])
                recorded.extend(payload[1])
                reported.add(worker)
            else:  # the first error ends the evaluation
                raise RuntimeError(f"an evaluation worker failed: {payload}")
    finally:
        for process in processes:
            if len(reported) < len(processes):
                process.terminate()
            process.join(timeout=10)
    return rows, recorded


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


#: Fields that shape the observation vector: a model only fits envs that agree on them.
OBSERVATION_SHAPING_FIELDS = ("n_agents", "lidar_rays")


def check_model_fits(trained: TrainedModel, config: FormationConfig) -> None:
    """Raise ``ValueError`` naming every difference if ``trained`` cannot act in envs of ``config``."""
    differences = [
        f"{name}={getattr(trained.config, name)} in the model, {getattr(config, name)} in the env"
        for name in OBSERVATION_SHAPING_FIELDS
        if getattr(trained.config, name) != getattr(config, name)
    ]
    if differences:
        raise ValueError("the model does not fit this env's observations: " + "; ".join(differences))
    state = trained.normalizer_state
    missing = [key for key in STATE_KEYS if key not in state]
    if missing:
        raise ValueError(f"the normaliser statistics lack {missing}")
    mask = FormationEnv(config).binary_observation_mask
    if int(np.asarray(state["agent_obs_dim"])) != mask.size or not np.array_equal(np.asarray(state["binary_mask"]), mask):
        raise ValueError(
            f"the normaliser statistics are for {int(np.asarray(state['agent_obs_dim']))} features with other flags; "
            f"this env's observations have {mask.size}"
        )


def model_fingerprint(path: str | os.PathLike[str]) -> dict[str, str]:
    """The file and SHA-256 of a saved model, to tell whether a stored evaluation is of the same model."""
    digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    return {"file": str(path), "sha256": digest}


def evaluate(
    trained: TrainedModel,
    episodes: int,
    stage: int = 3,
    seed: int = 0,
    n_envs: int = 8,
    deterministic: bool = True,
    env_overrides: dict[str, Any] | None = None,
    n_workers: int = 1,
    record: int = 5,
    progress_bar: bool = False,
) -> EvaluationResult:
    """Play ``episodes`` episodes of ``stage`` with a trained policy; episode k starts from ``reset(seed=seed + k)``.

    With one worker the episodes are spread over ``n_envs`` teams whose observations go through the policy in one
    batch; with ``n_workers`` > 1 worker processes, worker w plays episodes w, w + n_workers, ... on its share of the
    teams. The scenarios depend only on ``seed``; the same (seed, n_envs, n_workers) gives bit-identical results.

    :param trained: the policy (anything with SB3's ``predict``) with its configuration and normaliser statistics
    :param episodes: number of episodes
    :param stage: curriculum stage of the scenarios (3 in the thesis's evaluations)
    :param seed: seed of the scenarios
    :param n_envs: teams played at once (over all workers)
    :param deterministic: use the policy's mean action (else sample; the sampling is seeded from ``seed``)
    :param env_overrides: :class:`FormationConfig` fields to change from the model's training configuration
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
    config = trained.config.replace(**{**(env_overrides or {}), "stage": stage})
    check_model_fits(trained, config)
    n_workers = min(n_workers, episodes)
    teams = np.array_split(np.arange(min(n_envs, episodes)), n_workers)
    jobs = [
        PlayJob(
            agent=trained.model.policy if hasattr(trained.model, "policy") else trained.model,
            config=config,
            normalizer_state=trained.normalizer_state,
            team_observations=trained.team_observations,
            seed=seed,
            episodes=list(range(worker, episodes, n_workers)),
            n_teams=len(teams[worker]),
            first_team=int(teams[worker][0]) if len(teams[worker]) else 0,
            deterministic=deterministic,
            record=record,
        )
        for worker in range(n_workers)
    ]
    with tqdm(total=episodes, desc="evaluating", unit="episode", disable=not progress_bar) as bar:
        if n_workers == 1:
            with torch.random.fork_rng():
                torch.manual_seed(seed)
                rows, recorded = play_episodes(jobs[0], on_episode=lambda: bar.update(1))
        else:
            rows, recorded = _play_in_workers(jobs, on_episode=lambda: bar.update(1))
    trajectories = _stack(config, seed, recorded)
    source = getattr(trained, "source", None)
    return EvaluationResult(
        episodes=sorted(rows, key=lambda row: row["episode"]),
        trajectories=trajectories,
        stage=stage,
        seed=seed,
        deterministic=deterministic,
        n_agents=config.n_agents,
        model=None if source is None else model_fingerprint(source),
    )


#: Columns of :func:`comparison_table` after the success rate: metric and heading.
TABLE_METRICS = (
    ("angle_error_deg", "angle error (deg)"),
    ("bearing_error", "bearing error"),
    ("neighbour_distance_error", "distance error (m)"),
    ("length", "steps"),
    ("collisions_obstacle", "obstacle collisions"),
    ("collisions_agent", "agent collisions"),
)


def comparison_table(summaries: dict[str, dict[str, Any]], over: str = "successful") -> str:
    """A Markdown table of evaluation summaries: success rate with its 95 % interval, then mean ± std of each metric.

    :param summaries: policy label -> :attr:`EvaluationResult.summary`
    :param over: ``"successful"`` (the thesis's choice) or ``"all"`` episodes for the means
    """
    if over not in ("successful", "all"):
        raise ValueError(f"over must be 'successful' or 'all', got {over!r}")
    headings = ["policy", "episodes", "success rate (95 % CI)", *(heading for _, heading in TABLE_METRICS)]
    lines = ["| " + " | ".join(headings) + " |", "|" + "|".join(["---"] + ["---:"] * (len(headings) - 1)) + "|"]
    for label, summary in summaries.items():
        low, high = summary["success_rate_ci95"]
        cells = [label, str(summary["episodes"]), f"{summary['success_rate']:.1%} ({low:.1%} - {high:.1%})"]
        for name, _ in TABLE_METRICS:
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


def evaluate_run(
    target: str | os.PathLike[str],
    protocol: dict[str, Any] | None = None,
    device: str = "auto",
    progress_bar: bool = False,
    out: str | os.PathLike[str] | None = None,
) -> EvaluationResult:
    """Evaluate a run folder's (or a model file's) model and write ``eval/`` beside it.

    :param target: a run folder (its final model, else its latest checkpoint) or a model ``.zip``
    :param protocol: :func:`evaluate` arguments (``episodes``, ``stage``, ``seed``, ``n_envs``, ``workers``,
        ``deterministic``, ``record``, ``env_overrides``); by default the thesis's: stage 3, 500 episodes in chapter 4,
        200 in chapter 5
    :param device: torch device
    :param progress_bar: show a progress bar
    :param out: folder for the files (default: ``eval/`` in the run folder, or beside the model file)
    """
    protocol = {key: value for key, value in (protocol or {}).items() if value is not None}
    trained = load_trained(target, device=device)
    episodes = protocol.pop("episodes", THESIS_EVALUATION_EPISODES[trained.config.layout])
    if "workers" in protocol:
        protocol["n_workers"] = protocol.pop("workers")
    result = evaluate(trained, episodes, progress_bar=progress_bar, **protocol)
    target = Path(target)
    result.save(out or (target if target.is_dir() else target.parent) / "eval")
    return result
