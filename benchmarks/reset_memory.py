"""Memory over many episode resets: resident memory of one ``FormationEnv`` playing short episodes.

Each episode is 5 steps of zero actions (ch5-bearing, n = 6, stage 3), so resets dominate. Prints the resident set
size every ``--every`` resets and its growth against the figure after the first ``--every`` resets, measured in the
same run (the reference: what importing, compiling and the first episodes cost).

Usage: ``python benchmarks/reset_memory.py [--resets 40000] [--every 5000]``
"""

from __future__ import annotations

import argparse
import os

import numpy as np

from sb3_formation import FormationConfig, FormationEnv


def resident_mib() -> float:
    """This process's resident set size (MiB), from ``/proc/self/statm`` (Linux)."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resets", type=int, default=40_000)
    parser.add_argument("--every", type=int, default=5_000)
    args = parser.parse_args()
    env = FormationEnv(FormationConfig.task("ch5-bearing", stage=3, max_steps=5))
    zero = {agent: np.zeros(2) for agent in env.possible_agents}
    reference = None
    for episode in range(1, args.resets + 1):
        env.reset(seed=episode)
        while env.agents:
            env.step(zero)
        if episode % args.every == 0:
            rss = resident_mib()
            reference = rss if reference is None else reference
            growth = rss - reference
            print(f"{episode:>7,} resets: {rss:7.1f} MiB resident, {growth:+6.1f} MiB since {args.every:,}", flush=True)


if __name__ == "__main__":
    main()
