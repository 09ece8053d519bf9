"""What the safety filter costs: filtered evaluation against unfiltered, and shielded training against unshielded,
measured side by side in one run and printed as ratios.

- Evaluation: ``evaluate`` of a target and of ``safe:<target>`` on the same episodes (stage 3 and a scene family, seeds
  from 10,000, 16 teams, one process, in this process after a warm-up that compiles everything), the two alternated
  ``--repeats`` times; medians of the wall time and their ratio.
- Training: agent-steps per second of PPO iterations of ``fast-ch5-bearing`` and of ``fast-ch5-bearing-shielded`` (the
  same recipe behind the filter), built as ``sb3-formation train`` builds them (14 teams of n = 6, one process);
  medians over ``--iterations`` iterations after one warm-up, alternated recipe by recipe.

Targets: filtered evaluation at most 1.5x the unfiltered time; shielded training at most 1.3x the unshielded time per
agent-step (at least 1 / 1.3 of its agent-steps per second).

Usage: ``python benchmarks/safety_cost.py [--episodes 48] [--repeats 3] [--iterations 4]``
"""

from __future__ import annotations

import argparse
import statistics
import time

from train_throughput import PhaseTimer

from sb3_formation.experiment.evaluation import evaluate
from sb3_formation.experiment.recipes import layered_settings, with_schedules
from sb3_formation.experiment.targets import load_policy
from sb3_formation.experiment.training import make_training_env, rollout_callbacks
from sb3_formation.sb3.model_files import algorithm_for
from sb3_formation.utils.machine import machine_line

TARGETS = ("controller:classical", "pretrained:ch5-bearing")
SCENES = ("curriculum", "clutter")
RECIPES = ("fast-ch5-bearing", "fast-ch5-bearing-shielded")


def evaluation_seconds(target: str, scenes: str, episodes: int) -> float:
    """Wall time (s) of evaluating ``target`` on ``episodes`` episodes of ``scenes`` (stage 3, seeds from 10,000)."""
    policy = load_policy(target)
    start = time.perf_counter()
    evaluate(policy, episodes, seed=10_000, env_overrides={"scenes": scenes}, record=0)
    return time.perf_counter() - start


def training_seconds_per_step(recipe: str, iterations: int) -> float:
    """Median wall time (s) per agent-step of ``iterations`` PPO iterations of ``recipe`` after one warm-up."""
    settings = layered_settings(recipe=recipe, n_envs=14, workers=1, seed=0, device="cpu")
    env = make_training_env(settings, stage=3)
    kwargs = settings.recipe.ppo_kwargs()
    model = algorithm_for(kwargs["policy"])(env=env, seed=0, device="cpu", **with_schedules(kwargs))
    timer = PhaseTimer()
    steps = model.n_steps * env.num_envs
    model.learn((iterations + 1) * steps, callback=[*rollout_callbacks(settings), timer])
    env.close()
    per_iteration = [rollout + training for rollout, training in zip(timer.rollouts[1:], timer.trainings[1:])]
    return statistics.median(per_iteration) / steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=48)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--iterations", type=int, default=4)
    args = parser.parse_args()
    print(f"{machine_line()}; medians of {args.repeats} runs of {args.episodes} episodes, {args.iterations} PPO iterations")
    worst = 0.0
    for target in TARGETS:
        for scenes in SCENES:
            for variant in (target, f"safe:{target}"):  # warm-up: imports, compilation, the policy's first calls
                evaluation_seconds(variant, scenes, 2)
            runs: dict[str, list[float]] = {target: [], f"safe:{target}": []}
            for _ in range(args.repeats):
                for variant in runs:
                    runs[variant].append(evaluation_seconds(variant, scenes, args.episodes))
            plain, safe = (statistics.median(values) for values in runs.values())
            worst = max(worst, safe / plain)
            print(f"evaluate {target:<24} {scenes:<10} unfiltered {plain:6.2f} s, filtered {safe:6.2f} s: {safe / plain:.2f}x")
    print(f"filtered evaluation, largest ratio {worst:.2f}x (target <= 1.5x): {'met' if worst <= 1.5 else 'NOT met'}")
    seconds: dict[str, list[float]] = {recipe: [] for recipe in RECIPES}
    for _ in range(2):  # alternated, twice, so that neither recipe has the machine's quiet minutes to itself
        for recipe in RECIPES:
            seconds[recipe].append(training_seconds_per_step(recipe, args.iterations))
    plain, shielded = (statistics.median(values) for values in seconds.values())
    print(
        f"train fast-ch5-bearing {1 / plain:,.0f} agent-steps/s, fast-ch5-bearing-shielded {1 / shielded:,.0f} agent-steps/s: "
        f"{shielded / plain:.2f}x the time per agent-step (target <= 1.3x): {'met' if shielded / plain <= 1.3 else 'NOT met'}"
    )


if __name__ == "__main__":
    main()
