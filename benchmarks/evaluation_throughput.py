"""Evaluation throughput: wall-clock seconds of ``sb3-formation evaluate pretrained:ch5-bearing`` (200 stage-3
episodes, the thesis's chapter-5 protocol), this checkout against a reference commit, in one run.

The command is run as a user runs it, in a fresh process (imports and the first compilations from Numba's cache
included), with the default options and with ``--workers 2``. The reference is another commit of this repository,
checked out into a temporary worktree and run with this virtual environment (its ``src/`` first on ``PYTHONPATH``).
Both must play the same episodes: the benchmark compares their ``episodes.csv`` without the ``team`` column (which
team played an episode depends on how many are played at once) and says whether they are identical.

Target: this checkout's default command at least 2.5x faster than the reference's default command.

Usage: ``python benchmarks/evaluation_throughput.py [--reference REV] [--episodes 200] [--repeats 3]``
"""

from __future__ import annotations

import argparse
import csv
import os
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path

from reference import ROOT, reference_checkout

from sb3_formation.utils.machine import machine_line

COMMAND = "import sys; from sb3_formation.cli import main; sys.exit(main())"
VARIANTS = {"default": [], "--workers 2": ["--workers", "2"]}


def run_evaluation(source: Path, episodes: int, options: list[str], out: Path) -> float:
    """Seconds of one ``evaluate`` command run from ``source`` (a checkout's ``src/``), writing into ``out``."""
    environment = {**os.environ, "PYTHONPATH": str(source)}
    arguments = ["evaluate", "pretrained:ch5-bearing", "--episodes", str(episodes), "--no-progress", "--out", str(out)]
    start = time.perf_counter()
    subprocess.run([sys.executable, "-c", COMMAND, *arguments, *options], env=environment, check=True, capture_output=True)
    return time.perf_counter() - start


def episode_rows(path: Path) -> list[dict[str, str]]:
    """The rows of an ``episodes.csv`` without the ``team`` column."""
    with path.open() as stream:
        return [{key: value for key, value in row.items() if key != "team"} for row in csv.DictReader(stream)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", help="a commit to compare against (default: none, this checkout only)")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(f"{machine_line()}; {args.episodes} episodes, medians of {args.repeats} runs")
    with tempfile.TemporaryDirectory() as folder, ExitStack() as stack:
        trees = {"this checkout": ROOT / "src"}
        if args.reference:
            trees[f"reference {args.reference}"] = stack.enter_context(reference_checkout(args.reference)) / "src"
        seconds: dict[tuple[str, str], float] = {}
        for name, source in trees.items():
            for variant, options in VARIANTS.items():
                out = Path(folder) / f"{len(seconds)}"
                runs = [run_evaluation(source, args.episodes, options, out) for _ in range(args.repeats)]
                seconds[name, variant] = statistics.median(runs)
                print(
                    f"{name:<28} {variant:<12} {seconds[name, variant]:7.1f} s   "
                    f"({args.episodes / seconds[name, variant]:.2f} episodes/s)",
                    flush=True,
                )
        episodes = {key: episode_rows(Path(folder) / f"{index}" / "episodes.csv") for index, key in enumerate(seconds)}
        if args.reference:
            reference = f"reference {args.reference}"
            for variant in VARIANTS:
                ratio = seconds[reference, "default"] / seconds["this checkout", variant]
                same = episodes["this checkout", variant] == episodes[reference, "default"]
                print(
                    f"this checkout {variant:<12} is {ratio:.2f}x the reference's default command; "
                    f"episode rows {'identical' if same else 'DIFFERENT'}"
                )


if __name__ == "__main__":
    main()
