"""Corridor bound: how far a better choice of side could take the shrinking controller in the corridor family.

``controller:shrinking`` meets the corridor's wall, follows it on the side its centroid drifts to and flips side by a
doubling search (``docs/controllers.md``). No agent sees the channel's mouth from where the team meets the wall, so the
side is a guess. This script plays the same corridor episodes (episode k from seed ``--seed`` + k, one team of the
recipe's task) three ways:

- ``own side``: the controller as it is;
- ``side from the map``: at the step its detour begins, the side is set towards the channel's mouth, read from the
  scene (privileged: no decentralised policy can do this); everything after (following, flips) is the controller's;
- ``side against the map``: the other side, the worst guess.

Success under ``side from the map`` bounds what any choice of side alone can give the controller. It prints success
with its 95 % Wilson interval and the median steps over successful episodes.

    python benchmarks/corridor_side_bound.py --episodes 100
"""

from __future__ import annotations

import argparse

import numpy as np

from sb3_formation import FormationEnv
from sb3_formation.controllers import ShrinkingController
from sb3_formation.controllers.shrinking import MEMORY_FIELDS
from sb3_formation.experiment.statistics import wilson_interval
from sb3_formation.experiment.targets import load_policy
from sb3_formation.utils.machine import machine_line

_SIGMA, _HIT = MEMORY_FIELDS.index("sigma"), MEMORY_FIELDS.index("hit")


def channel_centre(walls: np.ndarray) -> np.ndarray:
    """The middle of the corridor's channel (m): the mean of its two walls along x."""
    along = walls[np.abs(walls[:, 1] - walls[:, 3]) < 1e-9]
    return np.array([along[:, [0, 2]].mean(), along[:, [1, 3]].mean()])


def play(env: FormationEnv, controller: ShrinkingController, seed: int, side: float) -> tuple[bool, int]:
    """One corridor episode; ``side`` 0 leaves the side to the controller, +1 (-1) sets it towards (away from) the
    channel when the detour begins. Returns (success, steps)."""
    observations, _ = env.reset(seed=seed)
    rows = np.stack(list(observations.values()))
    centre, layout, state = channel_centre(env.walls), controller.layout, None
    while env.agents:
        began = None if state is None else state[:, _HIT] <= 0
        actions, state = controller.predict(rows, state)
        if side and began is not None and began.all() and (state[:, _HIT] > 0).all():
            goal_offset = rows[0, layout["centroid_goal_offset"]]  # c_g = goal - centroid, shared by the team
            to_channel = centre - (env.goal - goal_offset)
            cross = goal_offset[0] * to_channel[1] - goal_offset[1] * to_channel[0]
            state[:, _SIGMA] = side * (1.0 if cross > 0 else -1.0)  # sigma +1 turns the heading anti-clockwise
        observations, *_ = env.step(dict(zip(env.agents, actions)))
        rows = np.stack(list(observations.values())) if observations else rows
    summary = env.episode_summary()
    return bool(summary["success"]), int(summary["length"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--recipe", default="ch5-bearing", help="the recipe whose task the controller acts in")
    parser.add_argument("--episodes", type=int, default=100, help="corridor episodes per way")
    parser.add_argument("--seed", type=int, default=0, help="episode k plays the scene of seed + k")
    args = parser.parse_args()
    config = load_policy("controller:shrinking", recipe=args.recipe).config.replace(scenes="corridor")
    controller, env = ShrinkingController(config), FormationEnv(config)
    episodes = f"{args.episodes} corridor episodes from seed {args.seed}, n = {config.n_agents}"
    print(f"corridor side bound, {machine_line()}: {episodes}")
    print()
    print("| controller:shrinking | success (95 % CI) | steps (median over successes) |")
    print("|---|---:|---:|")
    for label, side in (("own side", 0.0), ("side from the map", 1.0), ("side against the map", -1.0)):
        played = [play(env, controller, args.seed + k, side) for k in range(args.episodes)]
        successes = sum(success for success, _ in played)
        low, high = wilson_interval(successes, args.episodes)
        steps = [length for success, length in played if success]
        median = f"{np.median(steps):.0f}" if steps else "-"
        print(f"| {label} | {successes / args.episodes:.0%} ({low:.0%} - {high:.0%}) | {median} |", flush=True)


if __name__ == "__main__":
    main()
