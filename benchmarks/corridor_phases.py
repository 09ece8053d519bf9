"""Corridor benchmark: where a policy spends its corridor episodes, before the channel, in it and after it.

For every target it plays ``--episodes`` episodes of the ``corridor`` scene family (episode k from seed ``--seed`` + k,
deterministic actions, every step recorded) and splits each episode at the first step its centroid is inside the
channel (between the two channel walls, past the entry end) and the first step after that it is past the exit end.
It prints, per target: success with its 95 % Wilson interval; the median and quartiles of the steps before the channel,
in it and after it over the successful episodes; and what became of the failed ones (never entered the channel, in it
at the time limit, or through it but short of the goal).

    python benchmarks/corridor_phases.py --targets controller:shrinking,controller:privileged-planner
"""

from __future__ import annotations

import argparse

import numpy as np

from sb3_formation.env.families import WALL_THICKNESS
from sb3_formation.experiment.evaluation import evaluate
from sb3_formation.experiment.statistics import wilson_interval
from sb3_formation.experiment.targets import load_policy
from sb3_formation.experiment.trajectories import Trajectories
from sb3_formation.utils.machine import machine_line


def channel_steps(trajectories: Trajectories, episode: int) -> tuple[int | None, int | None]:
    """The first step the centroid is inside the channel of episode ``episode``, and the first step after it that the
    centroid is past the channel's far end (``None`` when it never is).

    :param trajectories: recorded corridor episodes
    :param episode: a row of ``trajectories``
    """
    walls = trajectories.walls[episode]
    walls = walls[~np.isnan(walls[:, 0])]
    along = walls[np.abs(walls[:, 1] - walls[:, 3]) < 1e-9]  # the channel's two walls run along x
    start, end = along[:, [0, 2]].min(), along[:, [0, 2]].max()
    low, high = along[:, 1].min() + WALL_THICKNESS / 2, along[:, 1].max() - WALL_THICKNESS / 2
    length = int(trajectories.lengths[episode])
    centroids = trajectories.positions[episode, : length + 1].mean(axis=1)
    direction = 1.0 if trajectories.goals[episode, 0] > centroids[0, 0] else -1.0
    entry, exit_ = (start, end) if direction > 0 else (end, start)
    x, y = centroids[:, 0], centroids[:, 1]
    inside = (low < y) & (y < high) & ((x - entry) * direction > 0) & ((x - exit_) * direction < 0)
    if not inside.any():
        return None, None
    entered = int(np.argmax(inside))
    past = np.nonzero(((x - exit_) * direction > 0) & (np.arange(len(x)) > entered))[0]
    return entered, (int(past[0]) if len(past) else None)


def quartiles(values: list[int]) -> str:
    if not values:
        return "-"
    low, median, high = np.percentile(values, [25, 50, 75])
    return f"{median:.0f} ({low:.0f}-{high:.0f})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--targets", default="controller:shrinking,controller:privileged-planner", help="comma-separated")
    parser.add_argument("--recipe", default="ch5-bearing", help="the recipe controller targets act in")
    parser.add_argument("--episodes", type=int, default=100, help="corridor episodes per target")
    parser.add_argument("--seed", type=int, default=0, help="episode k plays the scene of seed + k")
    parser.add_argument("--n-envs", type=int, default=10, help="teams played at once")
    args = parser.parse_args()
    print(f"corridor benchmark, {machine_line()}: {args.episodes} corridor episodes from seed {args.seed} per target")
    print()
    print(
        "| target | success (95 % CI) | steps before the channel | steps in it | steps after it "
        "| failed: never in the channel | in it at the limit | through it, short of the goal |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for target in args.targets.split(","):
        policy = load_policy(target, recipe=args.recipe)
        result = evaluate(
            policy,
            episodes=args.episodes,
            seed=args.seed,
            n_envs=args.n_envs,
            env_overrides={"scenes": "corridor"},
            record=args.episodes,
        )
        trajectories = result.trajectories
        assert trajectories is not None  # every episode was recorded
        before, inside, after, failures = [], [], [], [0, 0, 0]
        for episode in range(len(trajectories.lengths)):
            entered, passed = channel_steps(trajectories, episode)
            length = int(trajectories.lengths[episode])
            if trajectories.success[episode] and entered is not None and passed is not None:
                before.append(entered)
                inside.append(passed - entered)
                after.append(length - passed)
            elif not trajectories.success[episode]:
                failures[0 if entered is None else 1 if passed is None else 2] += 1
        successes = int(np.sum(trajectories.success))
        low, high = wilson_interval(successes, args.episodes)
        print(
            f"| {target} | {successes / args.episodes:.0%} ({low:.0%} - {high:.0%}) | {quartiles(before)} "
            f"| {quartiles(inside)} | {quartiles(after)} | {failures[0]} | {failures[1]} | {failures[2]} |",
            flush=True,
        )
    print()
    print("steps: median (quartiles) over the successful episodes")


if __name__ == "__main__":
    main()
