"""Training runs: atomic checkpoints, periodic evaluation, stopping on signals, resuming (a run's recipe and run options
are in :mod:`~sb3_formation.experiment.recipes`, its folder's files in :mod:`~sb3_formation.experiment.runs`)."""

from __future__ import annotations

import copy
import json
import os
import shutil
import signal
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback, CallbackList
from stable_baselines3.common.logger import CSVOutputFormat, Logger, TensorBoardOutputFormat
from stable_baselines3.common.vec_env import VecEnv, unwrap_vec_wrapper

from sb3_formation.controllers.base import TeamPolicy
from sb3_formation.experiment.evaluation import evaluate
from sb3_formation.experiment.recipes import (
    TrainSettings,
    load_settings,
    read_safety_gains,
    residual_base,
    residual_policy,
    with_schedules,
    write_settings,
)
from sb3_formation.experiment.runs import (
    BEST_MODEL,
    BEST_NORMALIZER,
    FINAL_MODEL,
    FINAL_NORMALIZER,
    MODEL_FILE,
    NORMALIZER_FILE,
    STATE_FILE,
    latest_checkpoint,
    normalize_rewards,
    read_state,
    reward_normalizer,
    reward_normalizer_file,
    save_model,
)
from sb3_formation.safety.policy import SafePolicy
from sb3_formation.sb3.callbacks import (
    CollectionThreadsCallback,
    CurriculumCallback,
    FormationMetricsCallback,
    IterationProgressCallback,
    TimeBudgetCallback,
    TrainingClock,
    threads_beside_workers,
)
from sb3_formation.sb3.imitation import FrozenActorCallback, pretrain_actor
from sb3_formation.sb3.model_files import algorithm_for, is_trusted, load_model, restore_training_state
from sb3_formation.sb3.normalization import ScaleNormalizeVecEnv
from sb3_formation.sb3.residual import ResidualVecEnv
from sb3_formation.sb3.safety import SafetyVecEnv
from sb3_formation.sb3.trained import TrainedPolicy
from sb3_formation.sb3.vec_env import FormationVecEnv, make_formation_vec_env
from sb3_formation.utils.checks import check_path
from sb3_formation.utils.files import atomic_directory, atomic_write, folder_lock, holds_files

# Models and checkpoints ----------------------------------------------------------------------------------------


class RunCheckpointCallback(BaseCallback):
    """Write a checkpoint every ``every`` iterations, and stop training cleanly when a stop is requested.

    A checkpoint is a folder ``checkpoints/iteration_<k>`` written atomically (see :func:`atomic_directory`) after the
    k-th PPO update, holding the model (with its optimiser state), the normaliser statistics and ``state.json``
    (curriculum state, timestep count and training seconds so far). Only the ``keep`` most recent are kept. When a
    stop is requested the rollout under way is dropped: the checkpoint holds the state after the last completed
    iteration.

    :param run_dir: the run folder
    :param curriculum: the run's curriculum callback (its state goes into each checkpoint)
    :param clock: the run's training clock
    :param every: iterations between checkpoints
    :param recipe: the run's whole recipe (:meth:`~sb3_formation.experiment.recipes.Recipe.to_dict`), kept in
        ``state.json`` so that a resume can refuse a ``config.yaml`` edited since
    :param keep: checkpoints kept on disk
    """

    model: PPO  # the run's model (BaseCallback declares any algorithm)

    def __init__(
        self,
        run_dir: Path,
        curriculum: CurriculumCallback,
        clock: TrainingClock,
        every: int,
        recipe: dict[str, Any],
        keep: int = 3,
    ) -> None:
        super().__init__()
        self.recipe = recipe
        self.run_dir = run_dir
        self.curriculum = curriculum
        self.clock = clock
        self.every = every
        self.keep = keep
        self.stop_signal: int | None = None  # the signal that asked training to stop
        self._start: dict[str, Any] = {}  # the state at the start of the iteration under way (:meth:`drop_iteration`)
        self._update_announced = False  # the first update of a session says it started (an update may take minutes)

    def _on_step(self) -> bool:
        return self.stop_signal is None

    def _on_rollout_start(self) -> None:
        # a rollout starts after the previous iteration's update (SB3 calls train() after the rollout-end callbacks)
        iteration = self.curriculum.iteration
        if iteration > 0 and iteration % self.every == 0:
            self.save()
        rewards = reward_normalizer(cast(VecEnv, self.model.get_env()))
        self._start = copy.deepcopy(
            {
                "policy": self.model.policy.state_dict(),
                "optimizer": self.model.policy.optimizer.state_dict(),
                "curriculum": self.curriculum.state_dict(),
                "returns": None if rewards is None else rewards.ret_rms,
                "windows": {name: getattr(self.model, name) for name in ("ep_info_buffer", "ep_success_buffer")},
                "counters": {name: getattr(self.model, name) for name in ("_n_updates", "_episode_num")},
            }
        )

    def _on_rollout_end(self) -> None:
        # SB3 calls train() next: say once per session that the update is under way (later ones are in tensorboard/)
        if not self._update_announced:
            self._update_announced = True
            log = self.run_dir / "tensorboard"
            print(
                f"rollout collected: PPO update under way ({self.model.n_epochs} epochs; every iteration is logged in {log})"
            )
            sys.stdout.flush()

    def drop_iteration(self) -> None:
        """Put the model, its optimiser, the curriculum, the reward statistics and the episode windows back as they
        were when the iteration under way started (its update was stopped half way): :meth:`save` then writes the
        state after the last completed iteration, as after a stop during a rollout."""
        start = self._start
        self.model.policy.load_state_dict(start["policy"])
        self.model.policy.optimizer.load_state_dict(start["optimizer"])
        self.curriculum.load_state_dict(start["curriculum"])
        rewards = reward_normalizer(cast(VecEnv, self.model.get_env()))
        if rewards is not None:
            rewards.ret_rms = start["returns"]
        for name, value in {**start["windows"], **start["counters"]}.items():
            setattr(self.model, name, value)

    def save(self) -> Path:
        """Write a checkpoint of the state after the last completed iteration and return its folder.

        A checkpoint of that iteration already on disk (the one a resumed run started from) is kept as it is: it holds
        the same state, and replacing it would open the window of a folder swap for nothing.
        """
        iteration = self.curriculum.iteration
        # drop a partial rollout (the model was made with its env)
        self.model.num_timesteps = iteration * self.model.n_steps * cast(VecEnv, self.model.get_env()).num_envs
        target = self.run_dir / "checkpoints" / f"iteration_{iteration:06d}"
        if (target / STATE_FILE).is_file():
            return target
        with atomic_directory(target) as folder:
            save_model(self.model, cast(VecEnv, self.model.get_env()), folder, MODEL_FILE, NORMALIZER_FILE)
            state = {
                "num_timesteps": self.model.num_timesteps,
                "curriculum": self.curriculum.state_dict(),
                "training_seconds": self.clock.seconds,
                "recipe": self.recipe,
            }
            (folder / STATE_FILE).write_text(json.dumps(state, indent=2))
        for old in sorted((self.run_dir / "checkpoints").glob("iteration_*"))[: -self.keep]:
            shutil.rmtree(old, ignore_errors=True)
        return target


#: Seed of the periodic evaluation's episodes: other scenarios than the final evaluation's (seed 0), so that picking
#: the best model does not pick it on the episodes that then measure it.
PERIODIC_EVALUATION_SEED = 1_000_000
#: File beside ``best_model.zip`` holding the evaluation that made it the best.
BEST_EVALUATION = "best_evaluation.json"
#: Per-round records of the imitation pretraining (recipes with an ``imitation`` block).
IMITATION_FILE = "imitation.json"


class PeriodicEvaluation(BaseCallback):
    """Evaluate the deterministic policy every ``every`` iterations, as SB3's ``EvalCallback`` does, and keep the best.

    After the update of every ``every``-th iteration it plays ``episodes`` stage-3 episodes (from
    ``reset(seed=PERIODIC_EVALUATION_SEED + k)``) with the normaliser's statistics frozen, logs ``eval/success_rate`` and
    the mean over the episodes of every episode metric (``eval/angle_error_deg``, ``eval/collisions_agent``, ...), and
    saves ``best_model.zip`` with ``best_normalizer.npz`` whenever the success rate is the best so far (a lower mean
    angle error breaks ties). The best so far is kept in ``best_evaluation.json``, so a resumed run continues it.

    :param run_dir: the run folder
    :param settings: the run's settings (task configuration)
    :param curriculum: the run's curriculum (its iteration count)
    :param every: iterations between evaluations
    :param episodes: episodes per evaluation
    """

    model: PPO  # the run's model (BaseCallback declares any algorithm)

    def __init__(
        self, run_dir: Path, settings: TrainSettings, curriculum: CurriculumCallback, every: int, episodes: int
    ) -> None:
        super().__init__()
        self.run_dir, self.config, self.curriculum = run_dir, settings.recipe.config(), curriculum
        self.safety = read_safety_gains(settings.recipe.safety)  # a shielded run's policy acts behind its filter
        self.every, self.episodes = every, episodes
        best = run_dir / BEST_EVALUATION
        self.best: dict[str, Any] | None = json.loads(best.read_text()) if best.is_file() else None
        self.evaluated = curriculum.iteration

    def _on_step(self) -> bool:
        return True

    def _on_rollout_start(self) -> None:
        # a rollout starts after the previous iteration's update (as for checkpoints)
        if self.curriculum.iteration % self.every == 0:
            self.evaluate()

    def evaluate(self) -> None:
        """Evaluate now (once per iteration), log ``eval/*`` and keep the best model."""
        iteration = self.curriculum.iteration
        if iteration == self.evaluated:
            return
        self.evaluated = iteration
        env = cast(VecEnv, self.model.get_env())  # the model was made with its env
        normalizer = cast(ScaleNormalizeVecEnv, unwrap_vec_wrapper(env, ScaleNormalizeVecEnv))  # every training env's
        policy: TeamPolicy = TrainedPolicy(self.model.policy, self.config, normalizer.state_dict())
        if getattr(self.model, "residual", None):
            # attr-defined: see recipe_model; assignment: ResidualPolicy's config is a read-only property where TeamPolicy
            # (controllers/base.py) declares a settable attribute
            policy = residual_policy(self.model.residual, policy)  # type: ignore[attr-defined, assignment]
        if self.safety is not None:
            policy = SafePolicy(policy, self.safety)
        summary = evaluate(policy, self.episodes, stage=3, seed=PERIODIC_EVALUATION_SEED, n_envs=min(8, self.episodes)).summary
        self.logger.record("eval/success_rate", summary["success_rate"])
        for name, statistics in summary["all_episodes"].items():
            self.logger.record(f"eval/{name}", statistics["mean"])
        score = {"iteration": iteration, "success_rate": summary["success_rate"]}
        score["angle_error_deg"] = summary["all_episodes"]["angle_error_deg"]["mean"]
        if self.best is None or (score["success_rate"], -score["angle_error_deg"]) > (
            self.best["success_rate"],
            -self.best["angle_error_deg"],
        ):
            self.best = score
            save_model(self.model, env, self.run_dir, BEST_MODEL, BEST_NORMALIZER)
            atomic_write(self.run_dir / BEST_EVALUATION, json.dumps(score, indent=2))


class TrainingStopped(Exception):
    """Training stopped on SIGINT (Ctrl-C) or SIGTERM, after writing a checkpoint: ``resume`` continues it. The command
    line exits with the conventional code 128 + the signal's number (130, 143).

    :param signal_number: the signal that stopped it
    :param run_dir: the run folder
    :param checkpoint: the checkpoint written
    """

    def __init__(self, signal_number: int, run_dir: Path, checkpoint: Path | None) -> None:
        self.signal_number, self.run_dir = signal_number, run_dir
        name = signal.Signals(signal_number).name
        super().__init__(f"stopped by {name}; checkpoint {checkpoint}; continue with --resume {run_dir}")


class UpdateStopped(Exception):
    """Raised in place of an optimiser step of PPO's update once a stop was asked (:func:`stop_on_signals`)."""


@contextmanager
def stop_on_signals(checkpoint: RunCheckpointCallback, optimizer: torch.optim.Optimizer) -> Iterator[None]:
    """While active, SIGINT (Ctrl-C) and SIGTERM ask training to stop: during a rollout after the current step,
    during PPO's update before its next mini-batch, by :class:`UpdateStopped` from ``optimizer``'s ``step`` (no
    callback runs inside SB3's ``train``, and an update of many teams and epochs takes minutes). Either way the
    iteration under way is dropped and a checkpoint of the last completed one is written.

    :param checkpoint: the run's checkpoint callback (it keeps the signal)
    :param optimizer: the policy's optimiser
    """

    def request_stop(signum: int, frame: Any) -> None:
        checkpoint.stop_signal = signum

    step = optimizer.step

    def step_unless_stopped(*args: Any, **kwargs: Any) -> Any:
        if checkpoint.stop_signal is not None:
            raise UpdateStopped
        return step(*args, **kwargs)

    previous = {sig: signal.signal(sig, request_stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    optimizer.step = step_unless_stopped  # type: ignore[method-assign]
    try:
        yield
    finally:
        del optimizer.step  # the class's own again
        for sig, handler in previous.items():
            signal.signal(sig, handler)


# Runs ---------------------------------------------------------------------------------------------------------------


def make_training_env(settings: TrainSettings, stage: int, normalizer_path: Path | None = None) -> VecEnv:
    """The normalised VecEnv of a run, its teams placed for ``stage`` (with saved normaliser statistics to resume).

    The teams are :func:`~sb3_formation.sb3.vec_env.make_formation_vec_env`'s, with the recipe's team critic
    (:attr:`~sb3_formation.experiment.recipes.Recipe.team_critic`, the same rule). Observations are scaled by
    :class:`ScaleNormalizeVecEnv`; with reward normalisation SB3's ``VecNormalize`` divides the rewards by a running std
    of the discounted return on top of it.
    """
    recipe = settings.recipe
    config = recipe.training_config(stage=stage)
    teams = make_formation_vec_env(
        config,
        n_envs=recipe.n_envs,
        n_workers=settings.run.workers,
        normalize=False,
        team_critic=recipe.team_critic,
        team_sizes=recipe.sizes,
    )
    venv = cast(FormationVecEnv, teams)  # normalize=False: the teams themselves
    dim, mask = venv.agent_observation_dim, venv.binary_observation_mask
    gains = read_safety_gains(recipe.safety)
    if gains is not None:  # the filter acts on the raw observations and the final actions, below all else
        teams = SafetyVecEnv(venv, gains, recipe.safety_penalty)
    if recipe.residual is not None:  # the controller acts on the raw observations, below the normaliser
        base = residual_base(recipe.residual.to_dict(), config)
        teams = ResidualVecEnv(cast(FormationVecEnv, teams), *base)  # a filter forwards the rest
    if normalizer_path is None:
        env: VecEnv = ScaleNormalizeVecEnv(teams, dim, mask, center=recipe.training.center_observations)
    else:
        env = ScaleNormalizeVecEnv.load(normalizer_path, teams, training=True, agent_obs_dim=dim, binary_mask=mask)
    if not recipe.training.normalize_reward:
        return env
    reward_path = None if normalizer_path is None else normalizer_path.with_name(reward_normalizer_file(normalizer_path.name))
    return normalize_rewards(env, recipe.ppo_kwargs()["gamma"], reward_path)


def new_run_dir(settings: TrainSettings) -> Path:
    """A fresh folder ``<logdir>/<recipe>_<n>a_s<seed>_<timestamp>`` (``-2``, ``-3``, ... if taken)."""
    stamp = time.strftime("%Y%m%d-%H%M%S")
    name = f"{settings.recipe.name}_{settings.recipe.config().n_agents}a_s{settings.run.seed}_{stamp}"
    base = Path(settings.run.logdir) / name
    base.parent.mkdir(parents=True, exist_ok=True)
    for suffix in range(1, 1000):
        run_dir = base if suffix == 1 else base.with_name(f"{base.name}-{suffix}")
        try:
            run_dir.mkdir()
        except FileExistsError:
            continue
        return run_dir
    raise FileExistsError(f"no free run folder name next to {base}")


def train(settings: TrainSettings, command: str | None = None, run_dir: str | os.PathLike[str] | None = None) -> Path:
    """Run the whole curriculum of ``settings`` in a new run folder and return the folder.

    The environment and the model are built before the folder is made, so settings that fail there leave nothing
    behind.

    :param settings: the run's settings
    :param command: the command line to record in ``command.txt`` (default: this process's)
    :param run_dir: a new or empty folder (default: a new ``<logdir>/<recipe>_<n>a_s<seed>_<time>``); it is locked
        (:func:`~sb3_formation.utils.files.folder_lock`) while the run trains
    :raises ValueError: ``run_dir`` holds something already (a run: continue it with :func:`resume`)
    :raises RuntimeError: another process trains in ``run_dir``
    """
    if run_dir is not None:
        check_path(run_dir, "run folder")
        _check_unused(Path(run_dir))
    with _new_model(settings) as (model, curriculum, clock):
        run_dir = new_run_dir(settings) if run_dir is None else Path(run_dir)
        with folder_lock(run_dir, "run folder"):
            _check_unused(run_dir)  # again, under the lock: another process may have started in it meanwhile
            _start(model, settings, command, run_dir, curriculum, clock)
    return run_dir


def _check_unused(run_dir: Path) -> None:
    """Refuse a run folder that is a file or holds anything but its lock."""
    if holds_files(run_dir):
        raise ValueError(
            f"{run_dir} is not empty (a run is there already): continue it with --resume {run_dir}, or give an empty "
            "or new folder"
        )


@contextmanager
def _new_model(settings: TrainSettings) -> Iterator[tuple[PPO, CurriculumCallback, TrainingClock]]:
    """A new run's model on its training env, with its curriculum and clock; the env is closed on leaving."""
    clock = TrainingClock(settings.recipe.budget_seconds())
    curriculum = make_curriculum(settings, clock)
    env = make_training_env(settings, curriculum.stage)
    try:
        yield recipe_model(settings, env), curriculum, clock
    finally:
        env.close()


def recipe_model(settings: TrainSettings, env: VecEnv) -> PPO:
    """A new model of a run's recipe on its training env, carrying what :func:`load_trained` reads of it.

    :param settings: the run's settings
    :param env: its training env (:func:`make_training_env`)
    """
    kwargs = settings.recipe.ppo_kwargs()
    model = algorithm_for(kwargs["policy"])(
        env=env, seed=settings.run.seed, device=settings.run.device, verbose=0, **with_schedules(kwargs)
    )
    # attributes of this package's own, saved with the model (SB3's classes do not declare them)
    model.formation_config = settings.recipe.config().to_dict()  # type: ignore[attr-defined]
    recipe = settings.recipe.to_dict()  # the sections as plain data, as load_trained reads them
    model.residual = recipe["residual"]  # type: ignore[attr-defined]  # the model file says how its actions are meant (load_trained)
    model.safety = recipe["safety"]  # type: ignore[attr-defined]  # and whether they pass through the safety filter
    model.team_sizes = sorted(set(settings.recipe.sizes))  # type: ignore[attr-defined]  # and which team sizes it acts in
    return model


def _start(
    model: PPO,
    settings: TrainSettings,
    command: str | None,
    run_dir: Path,
    curriculum: CurriculumCallback,
    clock: TrainingClock,
) -> None:
    """Record the settings in ``run_dir`` (locked by the caller) and train ``model`` from the start."""
    write_settings(settings, run_dir / "config.yaml")
    atomic_write(run_dir / "command.txt", (command or " ".join(sys.argv)) + "\n")
    imitation = settings.recipe.imitation_settings()
    if imitation is not None:
        teacher = settings.recipe.teacher(settings.recipe.config())
        assert teacher is not None  # a recipe with an imitation block has a teacher
        records = pretrain_actor(model, teacher, imitation, seed=settings.run.seed, log=_print_imitation_round)
        atomic_write(run_dir / IMITATION_FILE, json.dumps(records, indent=2))
    _learn(model, settings, run_dir, curriculum, clock)


def _print_imitation_round(record: dict[str, float]) -> None:
    print(
        f"imitation round {record['round']}: {record['states']:,} states (teacher flies {record['teacher_share']:.0%} of "
        f"the steps), mean squared error {record['loss']:.4f}",
        flush=True,
    )


def resume(run_dir: str | os.PathLike[str], trusted: bool | None = None, progress_bar: bool | None = None) -> Path:
    """Continue a run from its latest checkpoint: same curriculum stage, timestep count, normaliser and optimiser.

    The model is built from the run's recipe and takes the checkpoint's tensors (read with ``weights_only``) and
    counters, so nothing in the checkpoint is unpickled. The random generators are re-seeded from the run's seed and
    the checkpoint's iteration, so resuming the same checkpoint twice gives the same continuation. The run folder is
    locked while it trains.

    :param trusted: load the checkpoint with SB3's ``load`` instead, unpickling what it holds (``None``: unless
        inside :func:`~sb3_formation.sb3.model_files.trust_pickle`)
    :param progress_bar: show the progress bar (``None``: as the run's options say); the one option a resume may
        change, as it changes nothing that is trained
    :raises ValueError: a checkpoint that needs unpickling (untrusted) or was trained with other settings, or a
        ``config.yaml`` whose recipe was edited since the checkpoint
    :raises RuntimeError: another process trains in ``run_dir``
    """
    run_dir = Path(run_dir)
    settings = load_settings(run_dir)
    if progress_bar is not None:
        settings = settings.replace_run(progress_bar=progress_bar)
    with folder_lock(run_dir, "run folder"):
        _resume(settings, run_dir, is_trusted(trusted))
    return run_dir


def plain_recipe(settings: TrainSettings) -> dict[str, Any]:
    """A run's whole recipe as JSON reads it back (lists, not tuples): what a checkpoint records."""
    return cast("dict[str, Any]", json.loads(json.dumps(settings.recipe.to_dict())))


def _check_recipe_unchanged(recorded: dict[str, Any] | None, recipe: dict[str, Any], run_dir: Path, checkpoint: Path) -> None:
    """Refuse to resume when ``config.yaml`` no longer holds the recipe the checkpoint was trained with. A key written
    as null on one side and left out on the other means the same (an unset keyword argument).

    :raises ValueError: a checkpoint that records no recipe, or naming every setting that differs, with both values
    """
    if recorded is None:
        raise ValueError(f"{checkpoint / STATE_FILE} records no recipe: the checkpoint is damaged")
    differences = [
        f"{key}: {old!r} in the checkpoint, {new!r} in config.yaml" for key, old, new in _differences(recorded, recipe)
    ]
    if not differences:
        return
    raise ValueError(
        f"{run_dir / 'config.yaml'} no longer holds the recipe {checkpoint.name} was trained with "
        f"({'; '.join(differences)}): put those settings back, or train a new run with them"
    )


def _differences(old: Any, new: Any, prefix: str = "") -> list[tuple[str, Any, Any]]:
    """The dotted keys at which two nested mappings differ, with both values (``None`` for a missing key)."""
    if not (isinstance(old, dict) and isinstance(new, dict)):
        return [] if old == new else [(prefix or "recipe", old, new)]
    return [
        difference
        for key in sorted(set(old) | set(new), key=str)
        for difference in _differences(old.get(key), new.get(key), f"{prefix}.{key}" if prefix else str(key))
    ]


def checkpoint_model(settings: TrainSettings, env: VecEnv, path: Path, trusted: bool = False) -> PPO:
    """The model of a run's checkpoint on its training env: the recipe's model with the checkpoint's state, or with
    ``trusted`` SB3's ``load`` of the file."""
    if trusted:
        return load_model(path, device=settings.run.device, trusted=True, env=env)
    model = recipe_model(settings, env)
    restore_training_state(model, path)
    return model


def _resume(settings: TrainSettings, run_dir: Path, trusted: bool = False) -> None:
    """Continue the run in ``run_dir`` (locked by the caller) from its latest checkpoint."""
    checkpoint = latest_checkpoint(run_dir)
    if checkpoint is None:
        if (run_dir / FINAL_MODEL).exists():
            raise FileNotFoundError(f"{run_dir} has no complete checkpoint under checkpoints/ to resume from")
        # killed before its first checkpoint (e.g. during imitation pretraining): the same seed repeats it exactly
        print(f"{run_dir} has no checkpoint yet: training it again from the start")
        command = run_dir / "command.txt"
        with _new_model(settings) as (model, curriculum, clock):
            _start(model, settings, command.read_text().strip() if command.exists() else None, run_dir, curriculum, clock)
        return
    for leftover in (run_dir / "checkpoints").glob(".iteration_*"):  # folders of a write that was killed
        shutil.rmtree(leftover, ignore_errors=True)
    state = read_state(checkpoint)
    _check_recipe_unchanged(state.get("recipe"), plain_recipe(settings), run_dir, checkpoint)
    clock = TrainingClock(settings.recipe.budget_seconds(), spent=state.get("training_seconds", 0.0))
    curriculum = make_curriculum(settings, clock)
    curriculum.load_state_dict(state["curriculum"])
    total = curriculum.total_iterations
    finals = all((run_dir / name).is_file() for name in (FINAL_MODEL, FINAL_NORMALIZER))
    if finals and total is not None and curriculum.iteration >= total:
        print(f"{run_dir} is finished ({total} iterations, {FINAL_MODEL} written): nothing to resume")
        return
    env = make_training_env(settings, curriculum.stage, checkpoint / NORMALIZER_FILE)
    try:
        model = checkpoint_model(settings, env, checkpoint / MODEL_FILE, trusted)
        model.set_random_seed(int(np.random.SeedSequence([settings.run.seed, curriculum.iteration]).generate_state(1)[0]))
        _learn(model, settings, run_dir, curriculum, clock)
    finally:
        env.close()


def make_curriculum(settings: TrainSettings, clock: TrainingClock) -> CurriculumCallback:
    """The run's curriculum: iterations per stage, the success gate and, under a time budget alone, the stages' shares
    of the time (:meth:`~sb3_formation.experiment.recipes.Recipe.stage_time_shares`).

    :param settings: the run's settings
    :param clock: the run's clock
    """
    return CurriculumCallback(
        settings.recipe.stage_iterations(),
        settings.recipe.success_threshold,
        time_shares=settings.recipe.stage_time_shares(),
        clock=clock,
    )


def rollout_callbacks(settings: TrainSettings) -> list[BaseCallback]:
    """A run's callbacks that act at every step of a rollout: its formation metrics and, beside worker processes
    (which poll on their cores while a rollout runs), torch's thread count kept to the other cores."""
    callbacks: list[BaseCallback] = [FormationMetricsCallback(settings.to_dict())]
    if settings.run.workers > 1:
        callbacks.append(CollectionThreadsCallback(threads_beside_workers(settings.run.workers)))
    return callbacks


def _learn(model: PPO, settings: TrainSettings, run_dir: Path, curriculum: CurriculumCallback, clock: TrainingClock) -> None:
    folder = run_dir / "tensorboard"
    folder.mkdir(exist_ok=True)
    # one CSV per session (SB3's CSV writer truncates its file); TensorBoard appends events to the same folder
    csv_name = "progress.csv" if curriculum.iteration == 0 else f"progress_from_iteration_{curriculum.iteration}.csv"
    model.set_logger(Logger(str(folder), [TensorBoardOutputFormat(str(folder)), CSVOutputFormat(str(folder / csv_name))]))
    budget = TimeBudgetCallback(clock)
    checkpoint = RunCheckpointCallback(run_dir, curriculum, clock, settings.run.checkpoint_every, plain_recipe(settings))
    callbacks: list[BaseCallback] = [curriculum, *rollout_callbacks(settings), budget, checkpoint]
    imitation = settings.recipe.imitation_settings()
    if imitation is not None and imitation.critic_warmup > 0:
        callbacks.append(FrozenActorCallback(imitation.critic_warmup, curriculum))
    every = settings.recipe.training.eval_every
    periodic = None
    if every is not None:
        episodes = settings.recipe.training.eval_episodes
        periodic = PeriodicEvaluation(run_dir, settings, curriculum, every, episodes)
        callbacks.append(periodic)
    total = curriculum.total_iterations
    if settings.run.progress_bar:
        callbacks.append(IterationProgressCallback(total, curriculum, curriculum.iteration))
    steps_per_iteration = model.n_steps * cast(VecEnv, model.get_env()).num_envs  # the model was made with its env
    # an open-ended curriculum (total None) trains until the time budget ends it
    remaining = sys.maxsize // 2 if total is None else (total - curriculum.iteration) * steps_per_iteration
    with stop_on_signals(checkpoint, model.policy.optimizer):
        if remaining > 0 and not clock.exhausted:
            try:
                model.learn(
                    total_timesteps=remaining,
                    callback=CallbackList(callbacks),
                    reset_num_timesteps=False,
                    progress_bar=False,
                )
            except UpdateStopped:  # the model is half updated: back to the start of its iteration
                checkpoint.drop_iteration()
        checkpoint.init_callback(model)  # (again) for when nothing was left to learn
        checkpoint.save()
        if periodic is not None and checkpoint.stop_signal is None:  # the last iteration's policy is a candidate too
            periodic.init_callback(model)
            periodic.evaluate()
            model.logger.dump(model.num_timesteps)
    if clock.exhausted:
        minutes = settings.recipe.training.minutes
        print(f"time budget of {minutes:g} min reached after {curriculum.iteration} iterations")
    if checkpoint.stop_signal is not None:
        raise TrainingStopped(checkpoint.stop_signal, run_dir, latest_checkpoint(run_dir))
    save_model(model, cast(VecEnv, model.get_env()), run_dir, FINAL_MODEL, FINAL_NORMALIZER)
