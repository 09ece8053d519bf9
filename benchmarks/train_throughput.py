"""Training throughput of PPO recipes: agent-steps per second, split into rollout collection and training, against a
reference measured in the same run: the bare gradient work of an iteration.

ch5-bearing, 14 teams of n = 6 (84 agent slots), each recipe's networks and PPO settings, its training env (observation
and reward normalisation as in ``sb3-formation train``) and the callbacks training runs at every step (formation
metrics; beside worker processes, torch's threads kept to the other cores):
- ``fast``: the fast recipe (``fast-ch5-bearing``: two [256, 256] MLPs, 256 steps per rollout, 5 epochs of 2048);
- ``thesis-mlp``: the thesis's settings (``ch5-bearing``: 128 steps, 10 epochs of 512) with chapter 4's MLP networks;
- ``thesis-gru``, ``thesis-lstm``: the same with chapter 5's recurrent networks.

The reference (the forward, backward and Adam step of the same networks on as many minibatches, without PPO's losses,
buffers or bookkeeping) gives this machine's ceiling for an iteration; the ratio of the whole loop's throughput to that
ceiling is the figure to compare across machines. Prints medians over the timed iterations (after one warm-up).

Targets: fast recipe: rollout at most 20 % of an iteration, at least 12,000 agent-steps/s and at least 80 %
of the ceiling; thesis recipe with the MLP: at least 85 % of the ceiling.

Usage: ``python benchmarks/train_throughput.py [--iterations 5] [--workers 1,2] [--recipes fast,thesis-mlp]``
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback

from sb3_formation.experiment.recipes import TrainSettings, layered_settings, with_schedules
from sb3_formation.experiment.training import make_training_env, rollout_callbacks
from sb3_formation.sb3.model_files import algorithm_for
from sb3_formation.sb3.recurrent import RecurrentFormationPolicy

#: recipe -> (recipe, recurrent cell or None for the MLP)
RECIPES = {
    "fast": ("fast-ch5-bearing", None),
    "thesis-mlp": ("ch5-bearing", None),
    "thesis-gru": ("ch5-bearing", "gru"),
    "thesis-lstm": ("ch5-bearing", "lstm"),
}


class PhaseTimer(BaseCallback):
    """Wall time of every rollout phase and of every training phase."""

    def __init__(self) -> None:
        super().__init__()
        self.rollouts: list[float] = []
        self.trainings: list[float] = []
        self._mark = 0.0

    def _on_rollout_start(self) -> None:
        now = time.perf_counter()
        if self.rollouts:  # the previous training phase ended now
            self.trainings.append(now - self._mark)
        self._mark = now

    def _on_rollout_end(self) -> None:
        now = time.perf_counter()
        self.rollouts.append(now - self._mark)
        self._mark = now

    def _on_training_end(self) -> None:
        self.trainings.append(time.perf_counter() - self._mark)

    def _on_step(self) -> bool:
        return True


def build(recipe: str, workers: int) -> tuple[PPO, TrainSettings]:
    """``recipe``'s model on its training env (stage 3, 14 teams, seed 0), as ``sb3-formation train`` makes them."""
    name, cell = RECIPES[recipe]
    recurrent = {"recurrent": cell is not None, **({"cell": cell} if cell else {})}
    settings = layered_settings(recipe=name, n_envs=14, workers=workers, seed=0, device="cpu", **recurrent)
    env = make_training_env(settings, stage=3)
    kwargs = settings.recipe.ppo_kwargs()
    return algorithm_for(kwargs["policy"])(env=env, seed=0, device="cpu", **with_schedules(kwargs)), settings


def measure(recipe: str, workers: int, iterations: int) -> tuple[float, float, float, int]:
    """Median rollout, training and reference seconds per iteration, and agent-steps per iteration, of ``recipe``."""
    model, settings = build(recipe, workers)
    env = model.get_env()
    timer = PhaseTimer()
    steps = model.n_steps * env.num_envs
    model.learn((iterations + 1) * steps, callback=[*rollout_callbacks(settings), timer])
    env.close()
    floor = statistics.median(gradient_floor(model) for _ in range(iterations))
    return statistics.median(timer.rollouts[1:]), statistics.median(timer.trainings[1:]), floor, steps


def gradient_floor(model: PPO) -> float:
    """Reference: seconds of the bare gradient work of one iteration (forward, backward and Adam step of the same
    networks on as many minibatches as PPO trains on), without PPO's losses, buffers or bookkeeping. Recurrent
    networks run over minibatches of whole sequences of ``max_sequence_length`` steps (no episode ends inside a
    rollout, as here)."""
    policy = model.policy
    samples = model.n_steps * model.get_env().num_envs
    minibatches = model.n_epochs * -(-samples // model.batch_size)
    recurrent = isinstance(policy, RecurrentFormationPolicy)
    length = (getattr(model, "max_sequence_length", None) or model.n_steps) if recurrent else 1
    shape = (length, model.batch_size // length) if recurrent else (model.batch_size,)
    observations = th.randn(*shape, *model.observation_space.shape)
    actions = th.zeros(*shape, 2)
    start = time.perf_counter()
    for _ in range(minibatches):
        if recurrent:
            values, log_prob, _ = policy.evaluate_sequences(observations, actions, policy.initial_state(shape[1]))
        else:
            values, log_prob, _ = policy.evaluate_actions(observations, actions)
        loss = values.square().mean() - log_prob.mean()
        policy.optimizer.zero_grad()
        loss.backward()
        policy.optimizer.step()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=5)
    parser.add_argument("--workers", default="1,2", help="processes stepping the teams, comma-separated")
    parser.add_argument("--recipes", default="fast,thesis-mlp", help=f"comma-separated: {', '.join(RECIPES)}")
    args = parser.parse_args()
    print(f"PPO throughput, ch5-bearing, 14 teams of n = 6; torch threads {th.get_num_threads()}")
    print(f"medians of {args.iterations} iterations after one warm-up")
    for recipe in args.recipes.split(","):
        for workers in (int(value) for value in args.workers.split(",")):
            rollout, training, floor, steps = measure(recipe, workers, args.iterations)
            total = rollout + training
            share, ceiling = rollout / total, floor / total
            print(
                f"  {recipe:<11} workers={workers}: rollout {rollout:5.2f} s + training {training:5.2f} s per iteration of "
                f"{steps} agent-steps -> {steps / total:,.0f} agent-steps/s; rollout share {share:.0%}"
            )
            print(
                f"{'':14}reference {floor:5.2f} s (ceiling {steps / floor:,.0f} agent-steps/s): training / reference "
                f"{training / floor:.2f}x, throughput / ceiling {ceiling:.0%}"
            )
            if recipe == "fast":
                verdict = "met" if share <= 0.2 and steps / total >= 12_000 and ceiling >= 0.8 else "NOT met"
                print(f"{'':14}target rollout <= 20 %, >= 12,000 agent-steps/s, >= 80 % of the ceiling: {verdict}")
            if recipe == "thesis-mlp":
                print(f"{'':14}target >= 85 % of the ceiling: {'met' if ceiling >= 0.85 else 'NOT met'}")


if __name__ == "__main__":
    main()
