"""SB3 callbacks: the thesis's curriculum, formation metrics for TensorBoard, a wall-clock budget, a progress bar and
torch's threads during collection.

A PPO *iteration* is one rollout of ``n_steps`` steps in every slot followed by one training phase; the callbacks
count iterations with ``_on_rollout_end``.
"""

from __future__ import annotations

import json
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any, cast

import numpy as np
import torch as th
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import HParam, TensorBoardOutputFormat
from stable_baselines3.common.utils import FloatSchedule

from sb3_formation.env.config import REWARD_TERMS
from sb3_formation.sb3.metrics import EPISODE_METRICS, SAFETY_METRICS, SUCCESS_RATE_TAG

#: Per team-episode metrics logged during training: TensorBoard tag -> key of the VecEnv's ``formation_episode`` summary.
TENSORBOARD_METRICS: dict[str, str] = {
    SUCCESS_RATE_TAG: "success",
    **{metric.tensorboard: name for name, metric in EPISODE_METRICS.items() if metric.tensorboard is not None},
}


#: The HParams tab's metrics: the scalars it shows beside a run's settings (the last value each run logged).
HPARAM_METRICS: tuple[str, ...] = (
    SUCCESS_RATE_TAG,
    "formation/angle_error_deg",
    "formation/bearing_error",
    "eval/success_rate",
    "eval/angle_error_deg",
)


def hparam_values(settings: dict[str, Any], prefix: str = "") -> dict[str, bool | str | float | None]:
    """A run's settings as SB3's ``HParam`` takes them: nested mappings flattened to ``env/v_max``-style names, lists
    and other values written as JSON text.

    :param settings: the settings (e.g. a run's resolved configuration)
    :param prefix: prefix of every name (for the recursion)
    """
    values: dict[str, bool | str | float | None] = {}
    for key, value in settings.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            values.update(hparam_values(value, f"{name}/"))
        elif value is None or isinstance(value, (bool, int, float, str)):
            values[name] = value
        else:
            values[name] = json.dumps(value)
    return values


def finished_episodes(infos: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The team-episode summaries (``formation_episode``) among one step's infos."""
    return [info["formation_episode"] for info in infos if "formation_episode" in info]


class CurriculumCallback(BaseCallback):
    """Advance the curriculum stage 1 -> 2 -> 3 after a number of PPO iterations per stage (thesis 4.3, 5.3).

    With ``success_threshold`` a stage also ends early once the success rate over the last ``window`` team-episodes
    of that stage reaches it. With ``time_shares`` stages 1 and 2 end at shares of a time budget instead of after
    their iterations (checked at the end of each iteration). Stage changes reach every team through
    ``env_method("set_stage", ...)``: rewards change at once, placements at each team's next reset. The state (stage,
    iterations) is saved with checkpoints.

    :param iterations_per_stage: PPO iterations of stages 1, 2 and 3; the last may be ``None`` (open-ended: training
        is ended by something else, e.g. a :class:`TimeBudgetCallback`)
    :param success_threshold: success rate in [0, 1] that ends stages 1 and 2 early, or ``None``
    :param window: team-episodes in the rolling success rate
    :param verbose: 1 prints each stage change
    :param time_shares: fractions in [0, 1] of ``clock``'s budget after which stages 1 and 2 end (cumulative, e.g.
        ``(0.2, 0.4)``), or ``None`` (they end after their iterations)
    :param clock: the run's clock with its budget; needed with ``time_shares``
    """

    def __init__(
        self,
        iterations_per_stage: Sequence[int | None],
        success_threshold: float | None = None,
        window: int = 100,
        verbose: int = 0,
        time_shares: tuple[float, float] | None = None,
        clock: TrainingClock | None = None,
    ) -> None:
        super().__init__(verbose)
        iterations = tuple(None if value is None else int(value) for value in iterations_per_stage)
        if len(iterations) != 3 or None in iterations[:2] or any(value < 0 for value in iterations if value is not None):
            raise ValueError(
                f"iterations_per_stage must be three integers >= 0 (the last may be None), got {iterations_per_stage!r}"
            )
        if success_threshold is not None and not 0.0 <= success_threshold <= 1.0:
            raise ValueError(f"success_threshold must be in [0, 1] or None, got {success_threshold!r}")
        if not isinstance(window, int) or window < 1:
            raise ValueError(f"window must be an integer >= 1, got {window!r}")
        if time_shares is not None:
            valid = len(time_shares) == 2 and 0.0 <= time_shares[0] <= time_shares[1] <= 1.0
            if not valid or clock is None or clock.budget is None:
                raise ValueError(
                    f"time_shares must be two increasing fractions in [0, 1] with a clock that has a budget, got "
                    f"{time_shares!r} and {'no clock' if clock is None else f'a budget of {clock.budget!r}'}"
                )
        self.iterations_per_stage = iterations
        self.time_shares = time_shares
        self.clock = clock
        self.success_threshold = success_threshold
        self.window = window
        self.stage = 1
        self.iteration = 0
        self.stage_iteration = 0
        self.successes: deque[bool] = deque(maxlen=window)

    @property
    def total_iterations(self) -> int | None:
        """Iterations of the whole curriculum (``None`` if its last stage is open-ended)."""
        return None if self.iterations_per_stage[2] is None else sum(cast("Sequence[int]", self.iterations_per_stage))

    def state_dict(self) -> dict[str, Any]:
        """What a checkpoint must keep to resume the curriculum where it was."""
        return {
            "stage": self.stage,
            "iteration": self.iteration,
            "stage_iteration": self.stage_iteration,
            "successes": list(self.successes),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.stage = int(state["stage"])
        self.iteration = int(state["iteration"])
        self.stage_iteration = int(state["stage_iteration"])
        self.successes = deque((bool(value) for value in state["successes"]), maxlen=self.window)

    def _on_training_start(self) -> None:
        self._advance_finished_stages()
        self.training_env.env_method("set_stage", self.stage)

    def _on_step(self) -> bool:
        for episode in finished_episodes(self.locals["infos"]):
            if episode["stage"] == self.stage:
                self.successes.append(bool(episode["success"]))
        return True

    def _on_rollout_end(self) -> None:
        self.iteration += 1
        self.stage_iteration += 1
        early = (
            self.stage < 3
            and self.success_threshold is not None
            and len(self.successes) == self.window
            and float(np.mean(self.successes)) >= self.success_threshold
        )
        if early:
            self._next_stage("success rate reached")
        self._advance_finished_stages()

    def _advance_finished_stages(self) -> None:
        """Move past every stage whose iterations (or share of the time) are done; a stage of none is skipped at once."""
        reason = "iterations done" if self.time_shares is None else "its share of the time budget done"
        while self.stage < 3 and self._stage_done():
            self._next_stage(reason)

    def _stage_done(self) -> bool:
        if self.time_shares is None:  # stages of counted iterations (an open-ended stage 3 is never done)
            return self.stage_iteration >= cast(int, self.iterations_per_stage[self.stage - 1])
        clock = cast(TrainingClock, self.clock)  # time shares come with a clock
        return clock.seconds >= self.time_shares[self.stage - 1] * cast(float, clock.budget)

    def _next_stage(self, reason: str) -> None:
        self.stage += 1
        self.stage_iteration = 0
        self.successes.clear()
        if self.verbose:
            print(f"curriculum: stage {self.stage} from iteration {self.iteration} ({reason})")
        if self.training_env is not None:
            self.training_env.env_method("set_stage", self.stage)


class FormationMetricsCallback(BaseCallback):
    """Log formation metrics per team-episode to SB3's logger (and so to TensorBoard), once per iteration.

    Means over the last ``window`` finished team-episodes (as SB3 does for ``rollout/ep_rew_mean``; the window runs
    across stage changes, and an episode counts for the stage it ended in) of
    ``formation/angle_error_deg``, ``formation/bearing_error``, ``formation/neighbour_distance_error``,
    ``episode/success_rate``, ``episode/length``, ``episode/collisions_obstacle``, ``episode/collisions_agent`` and
    ``reward/<term>`` (each reward term's per-step mean before its coefficient), plus ``curriculum/stage`` (the stage
    the iteration's rollout ran in). At the
    start of training it writes the run's settings through SB3's ``HParam`` (TensorBoard's HParams tab, with
    :data:`HPARAM_METRICS` as its metrics; names from :func:`hparam_values`) and a custom-scalars layout that groups
    these charts in TensorBoard.

    :param hyperparameters: the settings for the HParams tab (e.g. the resolved run configuration)
    :param window: team-episodes in the rolling means
    """

    def __init__(self, hyperparameters: dict[str, Any] | None = None, window: int = 100, verbose: int = 0) -> None:
        super().__init__(verbose)
        self.hyperparameters = hyperparameters or {}
        self.episodes: deque[dict[str, Any]] = deque(maxlen=window)

    def _on_training_start(self) -> None:
        metrics = dict.fromkeys(HPARAM_METRICS, 0.0)  # the tab shows each run's last logged value of these scalars
        hparams = HParam(hparam_values(self.hyperparameters), metrics)
        self.logger.record("hparams", hparams, exclude=("stdout", "log", "json", "csv"))
        writer = next(
            (output.writer for output in self.logger.output_formats if isinstance(output, TensorBoardOutputFormat)), None
        )
        if writer is not None:
            writer.add_custom_scalars(custom_scalars_layout())

    def _on_rollout_start(self) -> None:
        # recorded now, dumped after this rollout: the stage this iteration's rollout runs in
        self.logger.record("curriculum/stage", self.training_env.get_attr("stage", indices=[0])[0])

    def _on_step(self) -> bool:
        self.episodes.extend(finished_episodes(self.locals["infos"]))
        return True

    def _on_rollout_end(self) -> None:
        if not self.episodes:
            return
        for key, field in TENSORBOARD_METRICS.items():
            self.logger.record(key, float(np.mean([episode[field] for episode in self.episodes])))
        for name, metric in SAFETY_METRICS.items():  # shielded training (SafetyVecEnv)
            if metric.tensorboard is not None and all(name in episode for episode in self.episodes):
                self.logger.record(metric.tensorboard, float(np.mean([episode[name] for episode in self.episodes])))
        for term in REWARD_TERMS:
            self.logger.record(f"reward/{term}", float(np.mean([episode["reward_terms"][term] for episode in self.episodes])))


def custom_scalars_layout() -> dict[str, dict[str, list]]:
    """TensorBoard custom-scalars layout: one category per namespace, one chart per metric."""
    return {
        "formation": {key.split("/")[1]: ["Multiline", [key]] for key in TENSORBOARD_METRICS if key.startswith("formation/")},
        "episode": {
            **{key.split("/")[1]: ["Multiline", [key]] for key in TENSORBOARD_METRICS if key.startswith("episode/")},
            "return": ["Multiline", ["rollout/ep_rew_mean"]],
        },
        "reward terms": {"terms": ["Multiline", [f"reward/{term}" for term in REWARD_TERMS]]},
        "curriculum": {"stage": ["Multiline", ["curriculum/stage"]]},
        "ppo": {
            "losses": ["Multiline", ["train/policy_gradient_loss", "train/value_loss"]],
            "kl": ["Multiline", ["train/approx_kl"]],
            "clip fraction": ["Multiline", ["train/clip_fraction"]],
        },
    }


class TrainingClock:
    """Wall-clock seconds spent training a run, over all its sessions, and an optional budget of them.

    :param budget: seconds of training allowed, or ``None``
    :param spent: seconds spent in earlier sessions of the run (a resumed run continues its clock)
    """

    def __init__(self, budget: float | None = None, spent: float = 0.0) -> None:
        if budget is not None and not budget > 0:
            raise ValueError(f"the time budget must be > 0 seconds, got {budget!r}")
        self.budget = budget
        self._spent = float(spent)
        self._started: float | None = None

    def start(self) -> None:
        """Start (or continue) counting."""
        if self._started is None:
            self._started = time.monotonic()

    def stop(self) -> None:
        """Stop counting (the time until now is kept)."""
        self._spent, self._started = self.seconds, None

    @property
    def seconds(self) -> float:
        """Seconds spent so far."""
        return self._spent + (0.0 if self._started is None else time.monotonic() - self._started)

    def progress_remaining(self) -> float:
        """The fraction of the budget left, in [0, 1] (1 without a budget), as SB3's ``progress_remaining``."""
        return 1.0 if self.budget is None else max(0.0, 1.0 - self.seconds / self.budget)

    @property
    def exhausted(self) -> bool:
        """Whether the budget is spent."""
        return self.budget is not None and self.seconds >= self.budget


class ClockedSchedule:
    """An SB3 schedule driven by whichever budget is further along: SB3's progress in timesteps, or a wall clock.

    It is called with SB3's ``progress_remaining`` and evaluates ``schedule`` at the smaller of that and the clock's
    remaining fraction. Pickled (in a saved model) it is the plain ``schedule``: the clock belongs to one session.

    :param schedule: a function of ``progress_remaining`` (1 -> 0)
    :param clock: the run's clock with its budget
    """

    def __init__(self, schedule: Callable[[float], float], clock: TrainingClock) -> None:
        self.schedule, self.clock = schedule, clock

    def __call__(self, progress_remaining: float) -> float:
        return float(self.schedule(min(progress_remaining, self.clock.progress_remaining())))

    def __reduce__(self) -> tuple[Any, ...]:
        return FloatSchedule, (self.schedule,)


class TimeBudgetCallback(BaseCallback):
    """Count the run's training time and, with a budget, end training at the first iteration boundary past it.

    With a budget the PPO schedules (learning rate, clip ranges) run over the budget too (see :class:`ClockedSchedule`):
    a linear decay reaches its floor when the time is up, or when the timestep budget is, whichever comes first. The
    iteration under way when the time runs out is completed; the rollout that would start after it is not collected.

    :param clock: the run's clock (its ``seconds`` go into checkpoints; a resumed run passes them back)
    """

    def __init__(self, clock: TrainingClock) -> None:
        super().__init__()
        self.clock = clock
        self.out_of_time = False

    def _on_training_start(self) -> None:
        self.clock.start()
        if self.clock.budget is None:
            return
        self.model.lr_schedule = ClockedSchedule(self.model.lr_schedule, self.clock)
        for name in ("clip_range", "clip_range_vf"):
            if getattr(self.model, name, None) is not None:
                setattr(self.model, name, ClockedSchedule(getattr(self.model, name), self.clock))

    def _on_rollout_start(self) -> None:
        self.out_of_time = self.clock.exhausted

    def _on_step(self) -> bool:
        return not self.out_of_time

    def _on_training_end(self) -> None:
        self.clock.stop()


def threads_beside_workers(workers: int) -> int:
    """Torch threads for this process while ``workers`` processes (this one included) step teams: one core fewer
    per worker process, at least one (the workers poll for the next step on their cores)."""
    return max(1, th.get_num_threads() - (workers - 1))


@contextmanager
def torch_threads(threads: int) -> Iterator[None]:
    """Run the block with ``threads`` torch threads, then restore torch's count."""
    before = th.get_num_threads()
    th.set_num_threads(threads)
    try:
        yield
    finally:
        th.set_num_threads(before)


class CollectionThreadsCallback(BaseCallback):
    """Torch's thread count while rollouts are collected: ``threads`` then, torch's own again for training.

    The worker processes of a :class:`~sb3_formation.sb3.vec_env.FormationVecEnv` poll for the next step on their
    cores during a rollout; torch threads there would fight them (``benchmarks/rollout_breakdown.py`` on 2 cores with
    one worker: a fast-recipe rollout took 0.89 s with torch's 2 threads, 0.38 s with 1).

    :param threads: torch threads during collection
    """

    def __init__(self, threads: int) -> None:
        super().__init__()
        self.threads = threads
        self._training_threads: int | None = None

    def _on_rollout_start(self) -> None:
        self._training_threads = th.get_num_threads()
        th.set_num_threads(self.threads)

    def _on_rollout_end(self) -> None:
        if self._training_threads is not None:
            th.set_num_threads(self._training_threads)
            self._training_threads = None

    def _on_training_end(self) -> None:  # also after a rollout that a callback stopped
        self._on_rollout_end()

    def _on_step(self) -> bool:
        return True


class IterationProgressCallback(BaseCallback):
    """A tqdm progress bar over PPO iterations showing stage, steps per second and the rolling success rate.

    :param total_iterations: iterations of the whole run (``None``: unknown, e.g. under a time budget)
    :param curriculum: the run's curriculum callback (for the stage and the success rate)
    :param initial_iteration: iterations already done (when resuming)
    """

    def __init__(self, total_iterations: int | None, curriculum: CurriculumCallback, initial_iteration: int = 0) -> None:
        super().__init__()
        self.total_iterations = total_iterations
        self.curriculum = curriculum
        self.initial_iteration = initial_iteration
        self.successes: deque[bool] = deque(maxlen=100)
        self.bar: Any = None

    def _on_training_start(self) -> None:
        from tqdm.auto import tqdm

        self.bar = tqdm(total=self.total_iterations, initial=self.initial_iteration, unit="it", dynamic_ncols=True)
        self._start = (time.perf_counter(), self.num_timesteps)

    def _on_step(self) -> bool:
        self.successes.extend(bool(episode["success"]) for episode in finished_episodes(self.locals["infos"]))
        return True

    def _on_rollout_end(self) -> None:
        elapsed = time.perf_counter() - self._start[0]
        speed = (self.num_timesteps - self._start[1]) / max(elapsed, 1e-9)
        success = f"{np.mean(self.successes):.0%}" if self.successes else "-"
        self.bar.set_postfix_str(f"stage {self.curriculum.stage}, {speed:,.0f} agent-steps/s, success {success}")
        self.bar.update(1)

    def _on_training_end(self) -> None:
        if self.bar is not None:
            self.bar.close()
