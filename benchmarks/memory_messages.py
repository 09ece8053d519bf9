"""Memory and messages, ablated: train a recipe's policy with both, with memory alone and with messages alone (and
with neither), on several seeds and one budget, then play every run on the benchmark's protocol
(``sb3-formation benchmark``: 100 episodes per scene set from seed 10,000, stage 3, teams of 6).

The variants change the recipe's ``policy:`` section only:

- ``both``: the recipe as it is (a recurrent policy with ``message_size`` M);
- ``memory``: ``message_size: 0``, memory without messages;
- ``messages``: ``memory: false``, messages without memory (the recurrent layers start every step from zeros);
- ``neither``: both switched off.

Each run trains with ``sb3-formation train`` in a process of its own, one after the other (each on the whole machine),
into ``--logdir/<variant>_s<seed>``; a run folder that holds a final model is kept, one without is resumed (so the
ablation may be stopped and started again). The table (``--logdir/benchmark/benchmark.md``) is the benchmark's, with
the training wall time of each run printed beside it.

    python benchmarks/memory_messages.py --seeds 0 --steps 3000000
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import yaml

from sb3_formation.experiment.benchmark import benchmark_table, run_benchmark
from sb3_formation.experiment.runs import FINAL_MODEL, STATE_FILE, latest_checkpoint
from sb3_formation.utils.machine import machine_line

#: The policy section's changes of each variant.
VARIANTS = {
    "both": {},
    "memory": {"message_size": 0},
    "messages": {"memory": False},
    "neither": {"message_size": 0, "memory": False},
}


def train(recipe: Path, seed: int, steps: int, run_dir: Path) -> float:
    """Train (or resume, or keep) one run; return the training wall time (s) its last checkpoint records."""
    command = [sys.executable, "-m", "sb3_formation.cli", "train"]
    if not (run_dir / FINAL_MODEL).exists():
        if run_dir.exists():
            command += ["--resume", str(run_dir)]
        else:
            command += ["--recipe", str(recipe), "--seed", str(seed), "--steps", str(steps), "--run-dir", str(run_dir)]
        subprocess.run([*command, "--no-progress", "--no-evaluate"], check=True)
    checkpoint = latest_checkpoint(run_dir)
    state = json.loads((checkpoint / STATE_FILE).read_text()) if checkpoint is not None else {}
    return float(state.get("training_seconds", float("nan")))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--recipe", default="residual-talk-scenes-ch5-bearing", help="a recipe with message_size > 0")
    parser.add_argument("--variants", default="both,memory,messages", help=f"comma-separated, of {list(VARIANTS)}")
    parser.add_argument("--seeds", default="0", help="comma-separated training seeds")
    parser.add_argument("--steps", type=int, default=3_000_000, help="training budget in agent-steps per run")
    parser.add_argument("--episodes", type=int, default=100, help="benchmark episodes per scene set")
    parser.add_argument("--logdir", type=Path, default=Path("runs/memory-messages"), help="folder of the runs")
    args = parser.parse_args()
    variants = args.variants.split(",")
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        parser.error(f"unknown variants {unknown}; variants: {list(VARIANTS)}")
    print(f"memory and messages ablation, {machine_line()}", flush=True)
    args.logdir.mkdir(parents=True, exist_ok=True)
    runs, seconds = [], {}
    for variant in variants:
        recipe = args.logdir / f"{variant}.yaml"
        recipe.write_text(yaml.safe_dump({"base": args.recipe, "name": f"{variant}", "policy": VARIANTS[variant]}))
        for seed in (int(seed) for seed in args.seeds.split(",")):
            run_dir = args.logdir / f"{variant}_s{seed}"
            seconds[run_dir.name] = train(recipe, seed, args.steps, run_dir)
            runs.append(run_dir)
    command = " ".join(["python", "benchmarks/memory_messages.py", *sys.argv[1:]])
    rows = run_benchmark(
        runs, [run.name for run in runs], args.logdir / "benchmark", episodes=args.episodes, workers=2, command=command
    )
    print(benchmark_table(rows))
    for name, spent in seconds.items():
        print(f"{name}: trained in {spent / 60:.1f} min")


if __name__ == "__main__":
    main()
