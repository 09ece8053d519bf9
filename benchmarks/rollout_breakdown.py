"""Where a rollout step's time goes, and two of the package's choices for a rollout against their alternative, in one run.

A recipe's model on its training env (``train_throughput.py``'s recipes; 14 teams of 6, stage 3) collects whole
rollouts with the callbacks training runs at every step. Prints, per step, medians over the rollouts:
- one process: the policy's forward pass (``policy.forward``), the VecEnv step (the whole wrapper chain) and the part of
  it inside ``FormationVecEnv.step_wait`` (the rest: the observation and reward normalisers), the rollout buffer, and
  the rest of SB3's loop;
- two processes (``n_workers=2``): a rollout with torch on 1 thread (what ``CollectionThreadsCallback`` sets) against
  torch's own 2 threads;
- the policy's forward pass on the same 84 observations with ``gaussian_actions`` against SB3's own Gaussian (torch's
  argument checks on).

Usage: ``python benchmarks/rollout_breakdown.py [--recipe fast] [--rollouts 5]``
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from collections.abc import Callable
from typing import Any

import torch as th
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import CallbackList
from train_throughput import RECIPES, build

from sb3_formation.experiment.training import rollout_callbacks
from sb3_formation.sb3.vec_env import FormationVecEnv


class Timed:
    """Replaces ``owner.name`` by a wrapper that adds the seconds of each call to ``seconds``."""

    def __init__(self, owner: Any, name: str) -> None:
        self.seconds = 0.0
        function: Callable[..., Any] = getattr(owner, name)

        def timed(*args: Any, **kwargs: Any) -> Any:
            start = time.perf_counter()
            try:
                return function(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - start

        setattr(owner, name, timed)


def rollout_seconds(model: PPO, callback: CallbackList) -> float:
    """Seconds of one whole rollout."""
    start = time.perf_counter()
    model.collect_rollouts(model.env, callback, model.rollout_buffer, model.n_steps)
    return time.perf_counter() - start


def prepared(model: PPO, settings: Any) -> CallbackList:
    """One warm-up iteration, then the training callbacks set up for :meth:`PPO.collect_rollouts`."""
    model.learn(model.n_steps * model.get_env().num_envs)
    callback = model._init_callback(CallbackList(rollout_callbacks(settings)))
    callback.on_training_start(locals(), globals())
    return callback


def breakdown(recipe: str, rollouts: int) -> dict[str, float]:
    """Median microseconds per rollout step of each part, one process."""
    model, settings = build(recipe, workers=1)
    callback = prepared(model, settings)
    venv = model.env
    while not isinstance(venv, FormationVecEnv):
        venv = venv.venv
    timers = {
        "forward": Timed(model.policy, "forward"),
        "env": Timed(model.env, "step"),
        "vec_env": Timed(venv, "step_wait"),
        "buffer": Timed(model.rollout_buffer, "add"),
    }
    rows: dict[str, list[float]] = {name: [] for name in [*timers, "total"]}
    for _ in range(rollouts):
        for timer in timers.values():
            timer.seconds = 0.0
        rows["total"].append(rollout_seconds(model, callback))
        for name, timer in timers.items():
            rows[name].append(timer.seconds)
    model.env.close()
    return {name: statistics.median(values) / model.n_steps * 1e6 for name, values in rows.items()}


def thread_rollouts(recipe: str, rollouts: int) -> dict[int, float]:
    """Median seconds of a rollout with two processes, torch on 1 thread and on 2 threads (interleaved)."""
    model, settings = build(recipe, workers=2)
    callback = prepared(model, dataclasses.replace(settings, workers=1))  # no CollectionThreadsCallback: set here
    seconds: dict[int, list[float]] = {1: [], 2: []}
    for _ in range(rollouts):
        for threads in seconds:
            th.set_num_threads(threads)
            seconds[threads].append(rollout_seconds(model, callback))
    model.env.close()
    th.set_num_threads(2)
    return {threads: statistics.median(values) for threads, values in seconds.items()}


def gaussian_forwards(recipe: str, calls: int = 2000) -> tuple[float, float]:
    """Mean microseconds of ``policy(obs)`` on 84 observations: with ``gaussian_actions``, and with SB3's own Gaussian
    (torch's argument checks on), in alternating blocks of calls."""
    model, _ = build(recipe, workers=1)
    policy = model.policy
    observations = th.as_tensor(model.env.reset())
    ours = policy._get_action_dist_from_latent

    def sb3_gaussian(latent_pi: th.Tensor) -> Any:
        mean = policy.action_scale * th.tanh(policy.action_net(latent_pi))
        return policy.action_dist.proba_distribution(mean, policy.log_std)

    totals = {"ours": 0.0, "sb3": 0.0}
    with th.no_grad():
        for _ in range(10):
            for name, function in (("ours", ours), ("sb3", sb3_gaussian)):
                policy._get_action_dist_from_latent = function
                start = time.perf_counter()
                for _ in range(calls // 10):
                    policy(observations)
                totals[name] += time.perf_counter() - start
    model.env.close()
    return totals["ours"] / calls * 1e6, totals["sb3"] / calls * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--recipe", default="fast", choices=sorted(RECIPES))
    parser.add_argument("--rollouts", type=int, default=5)
    args = parser.parse_args()
    th.set_num_threads(2)
    parts = breakdown(args.recipe, args.rollouts)
    rest = parts["total"] - parts["forward"] - parts["env"] - parts["buffer"]
    print(f"Rollout step of {args.recipe}, 14 teams of n = 6 (84 slots), one process; medians of {args.rollouts} rollouts")
    print(f"  whole step                         : {parts['total']:7.0f} us")
    print(f"  policy forward pass and sampling   : {parts['forward']:7.0f} us")
    print(f"  VecEnv step, whole wrapper chain   : {parts['env']:7.0f} us")
    print(f"    of it FormationVecEnv.step_wait  : {parts['vec_env']:7.0f} us")
    print(f"    of it the normalisers around it  : {parts['env'] - parts['vec_env']:7.0f} us")
    print(f"  rollout buffer                     : {parts['buffer']:7.0f} us")
    print(f"  rest of SB3's loop                 : {rest:7.0f} us")
    threads = thread_rollouts(args.recipe, args.rollouts)
    print(f"Two processes (n_workers=2), a whole rollout; medians of {args.rollouts}")
    print(f"  torch on 1 thread during collection: {threads[1]:5.2f} s")
    print(f"  torch on its 2 threads             : {threads[2]:5.2f} s  ({threads[2] / threads[1]:.2f}x)")
    ours, sb3 = gaussian_forwards(args.recipe)
    print("Policy forward pass on 84 observations, torch on 2 threads")
    print(f"  gaussian_actions (no argument checks): {ours:6.0f} us")
    print(f"  SB3's Gaussian (torch's checks)      : {sb3:6.0f} us  ({sb3 / ours:.2f}x)")


if __name__ == "__main__":
    main()
