"""Step time of this checkout against a reference commit, alternating fresh processes of the two so that both see the
same machine (a run of one after the other can differ by several per cent on a shared machine).

Each round runs one process per checkout and kind; a process builds the env, warms it up with 100 steps, then times
``--steps`` steps of random actions (ch5-bearing, stage 3, no episode ends). Kinds: ``vec_env`` (``FormationVecEnv``
of 14 teams of 6 in one process) and ``env`` (one ``FormationEnv`` through ``step_array``). Prints the median
microseconds per team-step over the rounds and the ratio of this checkout's agent-steps/s to the reference's.

Target: one ``FormationEnv`` at least 0.9x the reference's agent-steps/s, the VecEnv at least 1.0x.

Usage: ``python benchmarks/step_against_reference.py --reference REV [--rounds 8] [--steps 2500]``
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys

from reference import ROOT, reference_checkout

from sb3_formation.utils.machine import machine_line

#: What one process runs: builds the kind of env with the API both checkouts have, and prints us per team-step.
PROCESS = """
import sys, time
import numpy as np
from sb3_formation import FormationConfig, FormationEnv
from sb3_formation.sb3.vec_env import FormationVecEnv

kind, steps = sys.argv[1], int(sys.argv[2])
make = getattr(FormationConfig, "task", None) or FormationConfig.preset
config = make("ch5-bearing", stage=3, max_steps=10**6)
if kind == "vec_env":
    env = FormationVecEnv(config, n_envs=14)
    env.seed(0)
    env.reset()
    step, teams = env.step, 14
else:
    env = FormationEnv(config)
    env.reset(seed=0)
    step, teams = env.step_array, 1
actions = np.random.default_rng(0).uniform(-1.0, 1.0, (steps + 100, 6 * teams, 2))
for row in actions[:100]:
    step(row)
start = time.perf_counter()
for row in actions[100:]:
    step(row)
print((time.perf_counter() - start) / (steps * teams) * 1e6)
"""
KINDS = ("vec_env", "env")


def time_process(source: str, kind: str, steps: int) -> float:
    """Microseconds per team-step of one fresh process running the code of ``source`` (a ``src/`` folder)."""
    environment = {**os.environ, "PYTHONPATH": source}
    result = subprocess.run(
        [sys.executable, "-c", PROCESS, kind, str(steps)], env=environment, check=True, capture_output=True, text=True
    )
    return float(result.stdout.strip())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", required=True, help="the commit to compare against")
    parser.add_argument("--rounds", type=int, default=8)
    parser.add_argument("--steps", type=int, default=2500)
    args = parser.parse_args()
    print(f"{machine_line()}; {args.rounds} alternating rounds")
    with reference_checkout(args.reference) as tree:
        sources = {"this checkout": str(ROOT / "src"), f"reference {args.reference}": str(tree / "src")}
        times: dict[tuple[str, str], list[float]] = {(name, kind): [] for name in sources for kind in KINDS}
        for _ in range(args.rounds):
            for kind in KINDS:
                for name, source in sources.items():
                    times[name, kind].append(time_process(source, kind, args.steps))
    for kind in KINDS:
        mine, theirs = (statistics.median(times[name, kind]) for name in sources)
        print(
            f"{kind:8s}: this checkout {mine:6.1f} us/team-step, reference {theirs:6.1f}: {theirs / mine:.2f}x agent-steps/s"
        )


if __name__ == "__main__":
    main()
