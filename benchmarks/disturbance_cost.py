"""What disturbances cost: agent-steps per second of the batched VecEnv under each profile, against the ideal world in
the same run.

ch5-bearing at stage 3, random actions, 14 teams of 6 in one process (the VecEnv's batched stepping, resets included).
Prints medians over repeats, interleaved (ideal, realistic, harsh, ideal, ...) so that a change of the machine's load
falls on every profile alike.

Target: ``harsh`` costs at most 1.3x the ideal env's time per agent-step (its agent-steps/s at least 1 / 1.3 of the
ideal's). That the ideal world is as fast as before disturbances existed is ``env_throughput.py --reference REV``'s.

Usage: ``python benchmarks/disturbance_cost.py [--steps 500] [--repeats 5] [--teams 14]``
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from sb3_formation import FormationConfig
from sb3_formation.env.disturbances import PROFILES
from sb3_formation.sb3.vec_env import FormationVecEnv
from sb3_formation.utils.machine import machine_line

#: the most a profile may cost per agent-step, as a multiple of the ideal world's
TARGET = 1.3


def seconds_per_step(profile: str, teams: int, steps: int, seed: int) -> float:
    """Seconds per VecEnv step of ``teams`` teams under ``profile``, random actions."""
    config = FormationConfig.task("ch5-bearing", stage=3, disturbances=profile)
    env = FormationVecEnv(config, teams)
    env.seed(seed)
    env.reset()
    actions = np.random.default_rng(seed).uniform(-1.0, 1.0, (steps, env.num_envs, 2)).astype(np.float32)
    env.step(actions[0])  # compiled code warmed up
    start = time.perf_counter()
    for step_actions in actions:
        env.step(step_actions)
    elapsed = time.perf_counter() - start
    env.close()
    return elapsed / steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=500)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--teams", type=int, default=14)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(machine_line())
    times: dict[str, list[float]] = {profile: [] for profile in PROFILES}
    for repeat in range(args.repeats):
        for profile in PROFILES:
            times[profile].append(seconds_per_step(profile, args.teams, args.steps, args.seed + repeat))
    agents = args.teams * FormationConfig.task("ch5-bearing").n_agents
    median = {profile: statistics.median(values) for profile, values in times.items()}
    print(f"medians of {args.repeats} repeats of {args.steps} steps, {args.teams} teams of 6, one process")
    for profile in PROFILES:
        ratio = median[profile] / median["ideal"]
        print(
            f"  {profile:10s}: {median[profile] * 1e3:7.2f} ms/step  {agents / median[profile]:10,.0f} agent-steps/s  "
            f"cost {ratio:.2f}x the ideal's"
        )
    verdict = "met" if median["harsh"] / median["ideal"] <= TARGET else "NOT met"
    print(f"  harsh / ideal: {median['harsh'] / median['ideal']:.2f}x (target <= {TARGET}x: {verdict})")


if __name__ == "__main__":
    main()
