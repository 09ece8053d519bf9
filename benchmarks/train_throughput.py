"""Training throughput of the thesis PPO set-up: agent-steps per second, split into rollout collection and training.

ch5-bearing, n = 6, the thesis's 14 teams (84 agent slots), PPO with the thesis's settings and networks (n_steps 128,
batch 512, 10 epochs). Each iteration collects 128 x 84 = 10,752 agent-steps, then trains on them. Prints medians
over the timed iterations (after one warm-up iteration) for the MLP policy (chapter 4's networks) and the recurrent
ones of chapter 5 (GRU, LSTM), with one worker process (``--workers 1,2`` adds more).

Usage: ``python benchmarks/train_throughput.py [--iterations 4] [--workers 1] [--policies mlp,gru,lstm]``
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback

from sb3_formation import load_setup, make_formation_vec_env
from sb3_formation.experiment.runs import algorithm_for
from sb3_formation.sb3.recurrent import RecurrentFormationPolicy


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


def measure(workers: int, iterations: int, policy: str, preset: str = "ch5-bearing") -> tuple[float, float, float, int]:
    """Median rollout, training and gradient-floor seconds per iteration, and agent-steps per iteration.

    :param policy: ``"mlp"``, ``"gru"`` or ``"lstm"``
    """
    setup = load_setup(preset)
    env = make_formation_vec_env(preset, n_envs=setup.teams, seed=0, n_workers=workers)
    kwargs = setup.ppo_kwargs(recurrent=policy != "mlp", cell=None if policy == "mlp" else policy)
    model = algorithm_for(kwargs["policy"])(env=env, seed=0, device="cpu", **kwargs)
    timer = PhaseTimer()
    steps = model.n_steps * env.num_envs
    model.learn((iterations + 1) * steps, callback=timer)
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
    parser.add_argument("--iterations", type=int, default=4)
    parser.add_argument("--workers", default="1")
    parser.add_argument("--policies", default="mlp,gru,lstm")
    args = parser.parse_args()
    print(f"PPO throughput, ch5-bearing, n = 6, 14 teams, thesis networks and settings; torch threads {th.get_num_threads()}")
    print(f"medians of {args.iterations} iterations after one warm-up")
    throughput: dict[str, float] = {}
    for policy in args.policies.split(","):
        for workers in (int(value) for value in args.workers.split(",")):
            rollout, training, floor, steps = measure(workers, args.iterations, policy)
            total = rollout + training
            throughput.setdefault(policy, steps / total)
            print(
                f"  {policy:<4} workers={workers}: rollout {rollout:5.2f} s + training {training:5.2f} s per iteration of "
                f"{steps} agent-steps -> {steps / total:,.0f} agent-steps/s; rollout share {rollout / total:.0%}"
            )
            print(
                f"             reference, bare gradient work of an iteration {floor:5.2f} s: training / reference "
                f"{training / floor:.2f}x; the whole loop at this machine's gradient speed could reach at most "
                f"{steps / floor:,.0f} agent-steps/s"
            )
    if "mlp" in throughput:
        for policy in throughput.keys() - {"mlp"}:
            print(f"  {policy} / mlp throughput: {throughput[policy] / throughput['mlp']:.2f}x")
    print("  targets: >= 2,000 agent-steps/s overall, rollout < 20 % of an iteration")


if __name__ == "__main__":
    main()
