"""Training throughput of the thesis PPO set-up: agent-steps per second, split into rollout collection and training.

ch5-bearing, n = 6, the thesis's 14 teams (84 agent slots), PPO with the thesis's settings and networks (n_steps 128,
batch 512, 10 epochs). Each iteration collects 128 x 84 = 10,752 agent-steps, then trains on them. Prints medians
over the timed iterations (after one warm-up iteration) for one and two worker processes.

Usage: ``python benchmarks/train_throughput.py [--iterations 4] [--workers 1,2]``
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback

from sb3_formation import make_formation_vec_env
from sb3_formation.training import thesis_ppo_kwargs


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


def measure(workers: int, iterations: int, preset: str = "ch5-bearing") -> tuple[float, float, float, int]:
    """Median rollout, training and gradient-floor seconds per iteration, and agent-steps per iteration."""
    env = make_formation_vec_env(preset, seed=0, n_workers=workers)
    model = PPO(env=env, seed=0, device="cpu", **thesis_ppo_kwargs(preset))
    timer = PhaseTimer()
    steps = model.n_steps * env.num_envs
    model.learn((iterations + 1) * steps, callback=timer)
    env.close()
    floor = statistics.median(gradient_floor(model) for _ in range(iterations))
    return statistics.median(timer.rollouts[1:]), statistics.median(timer.trainings[1:]), floor, steps


def gradient_floor(model: PPO) -> float:
    """Reference: seconds of the bare gradient work of one iteration (forward, backward and Adam step of the same
    networks on as many minibatches as PPO trains on), without PPO's losses, buffers or bookkeeping."""
    policy = model.policy
    samples = model.n_steps * model.get_env().num_envs
    minibatches = model.n_epochs * -(-samples // model.batch_size)
    observations = th.randn(model.batch_size, *model.observation_space.shape)
    actions = th.zeros(model.batch_size, 2)
    start = time.perf_counter()
    for _ in range(minibatches):
        values, log_prob, _ = policy.evaluate_actions(observations, actions)
        loss = values.square().mean() - log_prob.mean()
        policy.optimizer.zero_grad()
        loss.backward()
        policy.optimizer.step()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=4)
    parser.add_argument("--workers", default="1,2")
    args = parser.parse_args()
    print(f"PPO throughput, ch5-bearing, n = 6, 14 teams, thesis networks and settings; torch threads {th.get_num_threads()}")
    print(f"medians of {args.iterations} iterations after one warm-up")
    for workers in (int(value) for value in args.workers.split(",")):
        rollout, training, floor, steps = measure(workers, args.iterations)
        total = rollout + training
        print(
            f"  workers={workers}: rollout {rollout:5.2f} s + training {training:5.2f} s per iteration of {steps} "
            f"agent-steps -> {steps / total:,.0f} agent-steps/s; rollout share {rollout / total:.0%}"
        )
        print(
            f"             reference, bare gradient work of an iteration {floor:5.2f} s: training / reference "
            f"{training / floor:.2f}x; the whole loop at this machine's gradient speed could reach at most "
            f"{steps / floor:,.0f} agent-steps/s"
        )
    print("  targets: >= 2,000 agent-steps/s overall, rollout < 20 % of an iteration")


if __name__ == "__main__":
    main()
