"""Evaluating a policy on fixed-seed curriculum episodes (thesis 4.4, 5.4): the protocol, its result and its files.

Episodes are played by :func:`~sb3_formation.experiment.rollouts.play_episodes` (episode k from ``reset(seed=s + k)``);
their rows are summarised with :mod:`~sb3_formation.experiment.statistics`, recorded steps stacked by
:mod:`~sb3_formation.experiment.trajectories`, and tables made by :mod:`~sb3_formation.experiment.reports`.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import torch
from tqdm.auto import tqdm

from sb3_formation.controllers.base import TeamPolicy
from sb3_formation.env.config import REWARD_TERMS
from sb3_formation.env.disturbances import disturbance_label, load_disturbances
from sb3_formation.env.scenes import DEFAULT_SCENES, scenes_named
from sb3_formation.experiment.rollouts import PlayJob, episode_config, play_episodes, seed_policy
from sb3_formation.experiment.sections import MAX_RECORDED_EPISODES as MAX_RECORDED_EPISODES
from sb3_formation.experiment.sections import EvaluationSection, check_record
from sb3_formation.experiment.statistics import check_summary, mean_and_std, wilson_interval
from sb3_formation.experiment.targets import Target
from sb3_formation.experiment.trajectories import Trajectories, stack_recordings
from sb3_formation.safety.policy import SafePolicy
from sb3_formation.sb3.callbacks import threads_beside_workers, torch_threads
from sb3_formation.sb3.metrics import EPISODE_METRICS, SAFETY_METRICS, WORLD_METRICS
from sb3_formation.utils.files import atomic_files, check_writable, file_digest, read_json

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
SUMMARY_FILE, EPISODES_FILE, TRAJECTORIES_FILE = "summary.json", "episodes.csv", "trajectories.npz"
#: Key of ``summary.json`` giving the SHA-256 of the other files of its evaluation (readers check them against it).
FILES_KEY = "files"
#: The protocol's fields that an evaluation summary records (:func:`stored_summary` matches them).
RECORDED_PROTOCOL = ("episodes", "stage", "seed", "deterministic")
#: Teams an evaluation plays at once by default: more teams per policy call spread the call's fixed cost, and the
#: engine steps them at once (``benchmarks/evaluation_throughput.py`` measures the default command)
EVALUATION_TEAMS = 16


@dataclass
class EvaluationResult:
    """Outcome of :func:`evaluate`.

    :param episodes: one row per episode, in episode order (the columns of :data:`EPISODE_COLUMNS`)
    :param trajectories: step-by-step records of the first episodes (``None`` if none were recorded)
    :param stage: curriculum stage of the episodes
    :param seed: episode k was played from ``reset(seed=seed + k)``
    :param deterministic: whether the policy's mean actions were used
    :param model: where the model came from (``file`` and ``sha256``), if known
    :param scenes: where the episodes were placed (``FormationConfig.scenes``)
    :param disturbances: the disturbances the episodes met (:meth:`~sb3_formation.env.disturbances.Disturbances.to_dict`;
        ``None``: the ideal world), recorded in the summary when there are some
    """

    episodes: list[dict[str, Any]]
    trajectories: Trajectories | None
    stage: int
    seed: int
    deterministic: bool
    n_agents: int
    model: dict[str, str] | None = None
    scenes: str = DEFAULT_SCENES
    disturbances: dict[str, Any] | None = None
    summary: dict[str, Any] = field(init=False)

    def __post_init__(self) -> None:
        successes = [episode for episode in self.episodes if episode["success"]]
        low, high = wilson_interval(len(successes), len(self.episodes))
        everything = mean_and_std(self.episodes)
        # the same metrics over the successes, a filtered policy's too when none succeeded (their means then None)
        successful = {name: {"mean": None, "std": None} for name in everything} | mean_and_std(successes)
        self.summary = {
            "episodes": len(self.episodes),
            "successes": len(successes),
            "success_rate": len(successes) / len(self.episodes),
            "success_rate_ci95": [low, high],
            "stage": self.stage,
            "scenes": self.scenes,
            **({} if self.disturbances is None else {"disturbances": self.disturbances}),
            "seed": self.seed,
            "deterministic": self.deterministic,
            "n_agents": self.n_agents,
            "model": self.model,
            "successful_episodes": successful,
            "all_episodes": everything,
            "episodes_with_contacts": {
                kind: sum(episode[f"collisions_{kind}"] > 0 for episode in self.episodes) for kind in ("agent", "obstacle")
            },
        }
        if self.episodes and "min_separation" in self.episodes[0]:  # a filtered policy's: the smallest over all
            self.summary["min_separation"] = min(episode["min_separation"] for episode in self.episodes)

    def save(self, folder: str | os.PathLike[str]) -> dict[str, Path]:
        """Write the evaluation's set into ``folder`` as one unit: ``episodes.csv``, ``trajectories.npz`` (if recorded;
        else one of an earlier evaluation is deleted) and ``summary.json``, which lists the SHA-256 of the others under
        :data:`FILES_KEY`. Other files of the folder are left alone. A failure (a full disk included) leaves the earlier
        set as it was, and two evaluations saved into one folder at once follow each other (see
        :func:`~sb3_formation.utils.files.atomic_files`).

        :param folder: the folder (created if needed)
        :return: the files written, by kind
        """
        folder = Path(folder)
        recorded = self.trajectories is not None
        names = [EPISODES_FILE, *([TRAJECTORIES_FILE] if recorded else []), SUMMARY_FILE]
        stale = () if recorded else (TRAJECTORIES_FILE,)
        with atomic_files(folder, names, remove=stale, what="evaluation folder") as temporaries:
            temporaries[EPISODES_FILE].write_text(self.episode_table())
            if self.trajectories is not None:
                self.trajectories.save(temporaries[TRAJECTORIES_FILE])
            digests = {name: file_digest(temporaries[name]) for name in names[:-1]}
            temporaries[SUMMARY_FILE].write_text(json.dumps({**self.summary, FILES_KEY: digests}, indent=2))
        kinds = {EPISODES_FILE: "episodes", TRAJECTORIES_FILE: "trajectories", SUMMARY_FILE: "summary"}
        return {kinds[name]: folder / name for name in names}

    def episode_table(self) -> str:
        """The text of ``episodes.csv``: a header of :data:`EPISODE_COLUMNS` (and of the safety metrics, for a filtered
        policy, and the mover metrics, for episodes with moving obstacles), then one row per episode."""
        table = io.StringIO()
        extra = [name for name in (*SAFETY_METRICS, *WORLD_METRICS) if self.episodes and name in self.episodes[0]]
        writer = csv.DictWriter(table, fieldnames=[*EPISODE_COLUMNS, *extra], lineterminator="\n")
        writer.writeheader()
        writer.writerows(self.episodes)
        return table.getvalue()


def model_fingerprint(path: str | os.PathLike[str]) -> dict[str, str]:
    """The file and SHA-256 of a saved model, to tell whether a stored evaluation is of the same model."""
    digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    return {"file": str(path), "sha256": digest}


def policy_identity(policy: TeamPolicy) -> dict[str, Any] | None:
    """What an evaluation summary records of its policy: a model file with its SHA-256, or a controller with its gains
    (``None`` for anything else)."""
    if isinstance(policy, SafePolicy):
        return {"safety": policy.filter.gains.to_dict(), "policy": policy_identity(policy.policy)}
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
    """Play ``episodes`` episodes of ``stage`` with a policy; episode k starts from ``reset(seed=seed + k)``. In a
    crossing every formation plays an episode: formations k to k + f - 1 fly the crossing drawn from ``seed + k`` (f
    formations), and ``episodes`` is rounded up to whole crossings.

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
    :param env_overrides: :class:`FormationConfig` fields to change from the policy's configuration (the episodes
        meet ideal disturbances unless ``disturbances`` is among them, whatever the policy was trained under)
    :param n_workers: processes playing the episodes
    :param record: record the step-by-step trajectories of the first ``record`` episodes (at most
        :data:`MAX_RECORDED_EPISODES`)
    :param progress_bar: show a tqdm progress bar of the episodes played
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if not 1 <= n_workers <= n_envs:
        raise ValueError(f"n_workers must be in [1, n_envs={n_envs}], got {n_workers}")
    check_record(record)
    config = episode_config(policy.config, env_overrides, stage)
    policy = policy.fit(config)
    unit = scenes_named(config.scenes).formations
    episodes = unit * -(-episodes // unit)  # whole crossings: a formation's episode each
    n_teams = min(n_envs, episodes)
    job = PlayJob(policy, config, seed, list(range(episodes)), n_teams, deterministic, record, min(n_workers, n_teams))
    with (
        tqdm(total=episodes, desc="evaluating", unit="episode", disable=not progress_bar) as bar,
        torch.random.fork_rng(),
        torch_threads(threads_beside_workers(job.n_workers)),
    ):
        seed_policy(policy, seed)
        rows, recorded = play_episodes(job, on_episode=lambda: bar.update(1))
    trajectories = stack_recordings(config, seed, recorded)
    return EvaluationResult(
        episodes=sorted(rows, key=lambda row: row["episode"]),
        trajectories=trajectories,
        stage=stage,
        seed=seed,
        deterministic=deterministic,
        n_agents=config.n_agents,
        model=policy_identity(policy),
        scenes=config.scenes,
        disturbances=None if config.disturbances.is_ideal else config.disturbances.to_dict(),
    )


def evaluate_target(
    target: Target | str | os.PathLike[str],
    protocol: EvaluationSection | None = None,
    *,
    changes: Mapping[str, Any] | None = None,
    workers: int = 1,
    env_overrides: dict[str, Any] | None = None,
    device: str = "auto",
    progress_bar: bool = False,
    out: str | os.PathLike[str] | None = None,
    disturbances: str | None = None,
) -> EvaluationResult:
    """Evaluate the policy a target names (:meth:`~sb3_formation.experiment.targets.Target.load`) and write its files.

    :param target: a :class:`~sb3_formation.experiment.targets.Target`, or what :meth:`Target.parse` reads (a run
        folder, a model file, ``controller:<name>``, ...)
    :param protocol: the evaluation protocol (default: the target's recipe's, :meth:`Target.protocol`; the thesis's:
        stage 3, 500 episodes in chapter 4, 200 in chapter 5)
    :param changes: fields of the protocol replaced (``None`` keeps its value), validated by the section
    :param workers: processes playing the episodes (``n_workers`` of :func:`evaluate`)
    :param env_overrides: :class:`FormationConfig` fields to change from the policy's configuration
    :param device: torch device
    :param progress_bar: show a progress bar
    :param out: folder for the files (default: :meth:`Target.evaluation_folder`)
    :param disturbances: the episodes meet these (a profile's name or a file,
        :func:`~sb3_formation.env.disturbances.load_disturbances`; default: ideal)
    :raises ValueError: the folder is inside the installed package (:func:`~sb3_formation.utils.files.check_writable`),
        the protocol is incomplete or invalid, or the disturbances are neither a profile nor a valid file
    """
    target = Target.parse(target)
    check_writable(out or target.evaluation_folder())  # before the work (the scene suffix does not move it)
    overrides = dict(env_overrides or {})
    label = "ideal" if disturbances is None else disturbance_label(disturbances)
    if disturbances is not None:
        overrides["disturbances"] = load_disturbances(disturbances)
    policy = target.load(device)
    changes = {name: value for name, value in (changes or {}).items() if value is not None}
    protocol = target.protocol(**changes) if protocol is None else protocol.replace(**changes)
    result = evaluate(policy, **protocol.kwargs(), env_overrides=overrides, n_workers=workers, progress_bar=progress_bar)
    result.save(out or target.evaluation_folder(result.scenes, label))
    return result


def load_summary(
    target: Target | str | os.PathLike[str], scenes: str = DEFAULT_SCENES, disturbances: str = "ideal"
) -> dict[str, Any]:
    """The stored evaluation summary of a target (see :meth:`~sb3_formation.experiment.targets.Target.evaluation_file`),
    checked against the other files of its evaluation (see :func:`check_evaluation_set`).

    :raises FileNotFoundError: none was written
    :raises ValueError: the file is not an evaluation summary, or the folder holds a mixed set
    """
    path = Target.parse(target).evaluation_file(SUMMARY_FILE, scenes, disturbances)
    summary = read_summary(path)
    check_evaluation_set(path.parent, summary)
    return summary


def read_summary(path: Path) -> dict[str, Any]:
    """The evaluation summary in the file ``path``.

    :raises ValueError: the file is not an evaluation summary, or is damaged (naming it)
    """
    summary = read_json(path)
    check_summary(summary, path)
    return cast("dict[str, Any]", summary)


def check_evaluation_set(folder: Path, summary: dict[str, Any], names: Collection[str] = ()) -> None:
    """Check that the files of an evaluation in ``folder`` are those its summary was written with (the SHA-256 under
    :data:`FILES_KEY`; summaries written before 0.2.0 list none and are not checked).

    :param folder: the evaluation's folder
    :param summary: its ``summary.json``
    :param names: files that must belong to the set too (e.g. the ``trajectories.npz`` about to be read)
    :raises ValueError: a file is missing, differs, or is not of the set: the folder mixes two evaluations
    """
    digests = summary.get(FILES_KEY)
    if digests is None:
        return
    for name in sorted({*digests, *names}):
        path = folder / name
        if name not in digests or not path.is_file() or file_digest(path) != digests[name]:
            raise ValueError(
                f"{path} is not of the evaluation in {folder / SUMMARY_FILE} (a write of the folder was cut short or "
                "is under way): run `sb3-formation evaluate` again"
            )


def load_trajectories(path: str | os.PathLike[str]) -> Trajectories:
    """The ``trajectories.npz`` at ``path``, checked against the ``summary.json`` beside it (if any), so that they are
    never the trajectories of another evaluation than the summary's.

    :raises FileNotFoundError: there is no such file
    :raises ValueError: the file is damaged or not of the evaluation beside it
    """
    path = Path(path)
    summary_path = path.parent / SUMMARY_FILE
    if path.name == TRAJECTORIES_FILE and path.is_file() and summary_path.is_file():
        check_evaluation_set(path.parent, read_summary(summary_path), names=[path.name])
    return Trajectories.load(path)


def stored_summary(
    target: Target | str | os.PathLike[str],
    protocol: EvaluationSection,
    scenes: str | None = None,
    disturbances: str | None = None,
) -> dict | None:
    """The target's stored evaluation summary if it is of the same policy (the model file's SHA-256, or the controller
    and its gains) under ``protocol`` (the fields a summary records, :data:`RECORDED_PROTOCOL`, that it sets) on
    ``scenes`` (``None``: the default scenes' evaluation, whatever scenes it records) and under ``disturbances`` (a
    profile's name or a file; ``None``: the ideal world), else ``None``."""
    target = Target.parse(target)
    wanted = {name: value for name, value in protocol.kwargs().items() if name in RECORDED_PROTOCOL}
    if scenes is not None:
        wanted["scenes"] = scenes
    wanted["disturbances"] = None if disturbances is None else load_disturbances(disturbances).to_dict()
    try:
        summary = load_summary(
            target, scenes or DEFAULT_SCENES, "ideal" if disturbances is None else disturbance_label(disturbances)
        )
        identity = policy_identity(target.load(device="cpu"))
    except (FileNotFoundError, ValueError):
        return None
    same_policy = identity is not None and summary.get("model") == identity
    return summary if same_policy and all(summary.get(key) == value for key, value in wanted.items()) else None
