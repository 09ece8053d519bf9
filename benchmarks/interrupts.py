"""How fast the commands stop: Ctrl-C of ``evaluate`` (one process and two workers), ``render`` and ``compare``, and
SIGTERM of ``train`` inside a long PPO update, each idle and beside two CPU-bound processes (the load of the test
suite's two workers), measured in one run.

Each command starts in a fresh session as a terminal would start it; once it is under way (``--settle`` seconds for
the evaluations, 10 s for the training, whose 16-step rollout is then over and whose update of 10^6 epochs would take
far longer), SIGINT goes to its whole process group (SIGTERM to the training process), and the time to its exit is
measured. Printed: the median and the largest of ``--repeats`` stops per command and condition, the ratio loaded /
idle of the medians, and whether each exited with the conventional code (130, 143) within the promised 2 s.

Usage: ``python benchmarks/interrupts.py [--repeats 3] [--settle 5]`` (run it alone: it makes its own load)
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import yaml

from sb3_formation.utils.machine import machine_line

#: The promise of the guarantees page: a stop within this many seconds.
PROMISE_SECONDS = 2.0
COMMANDS = {
    "evaluate --workers 2": ["evaluate", "controller:classical", "--episodes", "2000", "--workers", "2", "--n-envs", "4"],
    "evaluate": ["evaluate", "controller:classical", "--episodes", "2000", "--n-envs", "4"],
    "render": ["render", "controller:classical", "--episodes", "50", "--out", "v.gif"],
    "compare --workers 2": ["compare", "controller:classical", "controller:random", "--episodes", "2000", "--workers", "2"],
    "train (in a PPO update)": ["train", "--recipe", "long.yaml", "--iterations", "0,0,2", "--n-envs", "1", "--run-dir", "r"],
}
#: The commands that take ``--no-progress`` (render draws no progress bar).
QUIET = ("evaluate", "compare", "train")
#: A PPO update that runs for far longer than any stop may take.
LONG_UPDATE = {"base": "ch4-individual", "ppo": {"n_steps": 16, "batch_size": 16, "n_epochs": 1_000_000}}


def spin() -> None:
    """Busy loop: one core's load."""
    while True:
        pass


@contextlib.contextmanager
def load(processes: int) -> Iterator[None]:
    """``processes`` CPU-bound processes while the block runs."""
    spinners = [multiprocessing.Process(target=spin, daemon=True) for _ in range(processes)]
    for spinner in spinners:
        spinner.start()
    try:
        yield
    finally:
        for spinner in spinners:
            spinner.terminate()
            spinner.join()


def stop_seconds(name: str, settle: float) -> tuple[float, int]:
    """Start a command, stop it once under way, and return the seconds to its exit and its exit code."""
    arguments, training = COMMANDS[name], name.startswith("train")
    with tempfile.TemporaryDirectory() as folder:
        (Path(folder) / "long.yaml").write_text(yaml.safe_dump(LONG_UPDATE))
        process = subprocess.Popen(
            [sys.executable, "-m", "sb3_formation.cli", *arguments, *(["--no-progress"] if arguments[0] in QUIET else [])],
            cwd=folder,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            start_new_session=True,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # as under a terminal
        )
        time.sleep(10.0 if training else settle)
        if process.poll() is not None:
            message = process.communicate()[1].decode().strip().splitlines()[-1:]
            raise RuntimeError(f"{name} ended before it was stopped (exit code {process.returncode}): {message}")
        if training:
            process.send_signal(signal.SIGTERM)
        else:
            os.killpg(process.pid, signal.SIGINT)
        started = time.perf_counter()
        process.communicate(timeout=300)  # reads its progress output to the end, as a terminal would
        return time.perf_counter() - started, process.returncode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="stops per command and condition (default 3)")
    parser.add_argument("--settle", type=float, default=5.0, help="seconds an evaluation runs before Ctrl-C (default 5)")
    args = parser.parse_args()
    print(f"{machine_line()}: {args.repeats} stops per command and condition; load = 2 CPU-bound processes")
    print("| command | idle median (s) | idle max (s) | loaded median (s) | loaded max (s) | loaded / idle | exit codes |")
    print("|---|---:|---:|---:|---:|---:|---|")
    for name in COMMANDS:
        times: dict[str, list[float]] = {"idle": [], "loaded": []}
        codes = set()
        for _ in range(args.repeats):  # alternated, so that drifts of the machine touch both alike
            for condition in ("idle", "loaded"):
                with load(2 if condition == "loaded" else 0):
                    seconds, code = stop_seconds(name, args.settle)
                times[condition].append(seconds)
                codes.add(code)
        idle, loaded = (statistics.median(times[condition]) for condition in ("idle", "loaded"))
        within = "within" if max(times["loaded"] + times["idle"]) < PROMISE_SECONDS else "NOT within"
        print(
            f"| {name} | {idle:.2f} | {max(times['idle']):.2f} | {loaded:.2f} | {max(times['loaded']):.2f} | "
            f"{loaded / idle:.2f} | {sorted(codes)} ({within} {PROMISE_SECONDS:g} s) |"
        )


if __name__ == "__main__":
    main()
