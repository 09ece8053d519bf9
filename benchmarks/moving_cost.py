"""What a crowd costs: agent-steps per second of the engine with 20 walking pedestrians in every team's world, against
the same scenes without them, in the same run.

ch5-bearing, 14 teams of 6 in one engine, random actions. Every team's scene is a ``crowd`` scene drawn with 20
pedestrians (the family's most) that react to the agents; the reference plays the same scenes with the pedestrians
taken out (the static env: the same engine, placements and actions). Prints medians over repeats, interleaved (static,
crowd, static, ...) so that a change of the machine's load falls on both alike.

Target: a crowd of 20 costs at most 1.5x the static env's time per agent-step (its agent-steps/s at least 1 / 1.5 of
the static env's).

Usage: ``python benchmarks/moving_cost.py [--steps 500] [--repeats 5] [--teams 14]``
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time

import numpy as np

from sb3_formation import FormationConfig
from sb3_formation.env.engine import FormationEngine
from sb3_formation.env.families import MOVING_FAMILIES
from sb3_formation.env.scenarios import Scenario
from sb3_formation.utils.machine import machine_line

#: the most a crowd of 20 may cost per agent-step, as a multiple of the static env's
TARGET = 1.5
PEDESTRIANS = 20
CONFIG = FormationConfig.task("ch5-bearing", stage=3, scenes="crowd")


def crowd_scenes(teams: int, seed: int) -> list[Scenario]:
    """``teams`` crowd scenes of :data:`PEDESTRIANS` pedestrians each."""
    family = MOVING_FAMILIES["crowd"]
    assert family.traffic is not None
    crowded = dataclasses.replace(family, traffic=dataclasses.replace(family.traffic, count=(PEDESTRIANS, PEDESTRIANS)))
    rng = np.random.default_rng(seed)
    return [crowded.draw(CONFIG, 3, rng) for _ in range(teams)]


def seconds_per_step(scenes: list[Scenario], steps: int, seed: int) -> float:
    """Seconds per engine step of one team per scene, random actions."""
    engine = FormationEngine([CONFIG] * len(scenes))
    for team, scene in enumerate(scenes):
        engine.reset(team, seed=seed + team, scenario=scene)
    actions = np.random.default_rng(seed).uniform(-1.0, 1.0, (steps, len(scenes) * CONFIG.n_agents, 2))
    engine.step(actions[0])  # compiled code warmed up
    start = time.perf_counter()
    for step_actions in actions[1:]:
        engine.step(step_actions)
    return (time.perf_counter() - start) / (steps - 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--teams", type=int, default=14)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(machine_line())
    times: dict[str, list[float]] = {"static": [], "crowd": []}
    for repeat in range(args.repeats):
        crowd = crowd_scenes(args.teams, args.seed + repeat)
        static = [dataclasses.replace(scene, movers=()) for scene in crowd]
        times["static"].append(seconds_per_step(static, args.steps, args.seed + repeat))
        times["crowd"].append(seconds_per_step(crowd, args.steps, args.seed + repeat))
    agents = args.teams * CONFIG.n_agents
    median = {name: statistics.median(values) for name, values in times.items()}
    print(f"medians of {args.repeats} repeats of {args.steps} steps, {args.teams} teams of 6, one engine, one process")
    for name in times:
        print(f"  {name:7s}: {median[name] * 1e3:7.2f} ms/step  {agents / median[name]:10,.0f} agent-steps/s")
    ratio = median["crowd"] / median["static"]
    verdict = "met" if ratio <= TARGET else "NOT met"
    print(f"  crowd of {PEDESTRIANS} / static: {ratio:.2f}x the time per agent-step (target <= {TARGET}x: {verdict})")


if __name__ == "__main__":
    main()
