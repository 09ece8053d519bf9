"""How fast the commands stop: Ctrl-C of ``evaluate`` (one process and two workers), ``render`` and ``compare``, and
SIGTERM of ``train`` inside a long PPO update, each idle and beside one and two CPU-bound processes (two: the load of
the test suite's two workers), measured in one run.

Each command starts in a fresh session as a terminal would start it; once it is under way (it has printed the line
that says what it is about to do, and for the training the line that says its first PPO update, of 10^6 epochs, is
under way; plus ``--settle`` seconds for the evaluations, so that episodes are played), SIGINT goes to its whole
process group (SIGTERM to the training process), and the time to its exit is measured. Printed: the median and the
largest of ``--repeats`` stops per command and condition, the ratio loaded / idle of the medians, and whether each
exited with the conventional code (130, 143) within the promised 2 s.

Usage: ``python benchmarks/interrupts.py [--repeats 3] [--settle 2] [--commands "evaluate --workers 2"] [--loads 0,1,2]``
(run it alone: it makes its own load)
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
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

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
def cpu_load(processes: int) -> Iterator[None]:
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


#: The line each command prints once it is under way (what it is about to do; the training's first update).
READY = {"evaluate": "evaluating", "render": "rendering", "compare": "comparing", "train": "rollout collected"}


def stop_seconds(name: str, settle: float) -> tuple[float, int]:
    """Start a command, stop it once under way, and return the seconds to its exit and its exit code."""
    arguments, training = COMMANDS[name], name.startswith("train")
    with tempfile.TemporaryDirectory() as folder:
        (Path(folder) / "long.yaml").write_text(yaml.safe_dump(LONG_UPDATE))
        process = subprocess.Popen(
            [sys.executable, "-m", "sb3_formation.cli", *arguments, *(["--no-progress"] if arguments[0] in QUIET else [])],
            cwd=folder,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),  # as under a terminal
        )
        ready, errors = threading.Event(), []
        readers = [
            threading.Thread(target=_read_until, args=(process.stdout, READY[arguments[0]], ready), daemon=True),
            threading.Thread(target=_read_until, args=(process.stderr, None, None, errors), daemon=True),
        ]
        for reader in readers:
            reader.start()
        deadline = time.monotonic() + 600.0  # a hang guard
        while not ready.wait(0.1) and process.poll() is None:
            if time.monotonic() > deadline:
                process.kill()
                raise RuntimeError(f"{name} printed no {READY[arguments[0]]!r} line in 10 minutes")
        if not training:
            time.sleep(settle)  # episodes under way (a measurement's choice, not a synchronisation)
        if process.poll() is not None:
            raise RuntimeError(f"{name} ended before it was stopped (exit code {process.returncode}): {errors[-1:]}")
        if training:
            process.send_signal(signal.SIGTERM)
        else:
            os.killpg(process.pid, signal.SIGINT)
        started = time.perf_counter()
        process.wait(timeout=300)
        seconds = time.perf_counter() - started
        for reader in readers:
            reader.join(timeout=60)  # reads its output to the end, as a terminal would
        if process.returncode not in (130, 143):  # not the conventional code: say what the command printed
            print(f"{name}: exit code {process.returncode}; its stderr ends: {errors[-3:]}", file=sys.stderr)
        return seconds, process.returncode


def _read_until(stream: Any, start: str | None, ready: threading.Event | None, lines: list[str] | None = None) -> None:
    """Read ``stream`` to its end; set ``ready`` at the first line that starts with ``start``; keep lines in ``lines``."""
    for line in stream:
        if lines is not None:
            lines.append(line)
        if ready is not None and start is not None and line.startswith(start):
            ready.set()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="stops per command and condition (default 3)")
    parser.add_argument("--settle", type=float, default=2.0, help="seconds an evaluation plays before Ctrl-C (default 2)")
    parser.add_argument("--commands", help=f"comma-separated commands to measure (default all: {', '.join(COMMANDS)})")
    parser.add_argument("--loads", default="0,2", help="CPU-bound processes beside the command, per condition (default 0,2)")
    args = parser.parse_args()
    names = list(COMMANDS) if args.commands is None else [name.strip() for name in args.commands.split(",")]
    loads = [int(load) for load in args.loads.split(",")]
    unknown = sorted(set(names) - set(COMMANDS))
    if unknown or 0 not in loads:
        parser.error(f"unknown commands {unknown}; commands: {list(COMMANDS)}" if unknown else "--loads must include 0")
    print(f"{machine_line()}: {args.repeats} stops per command and condition; loads = {loads} CPU-bound processes")
    cells = " | ".join(f"{load} busy: median (s) | {load} busy: max (s)" for load in loads)
    ratios = " | ".join(f"{load} busy / idle" for load in loads if load)
    print(f"| command | {cells} | {ratios} | exit codes |")
    print("|---|" + "---:|" * (2 * len(loads) + len(loads) - 1) + "---|")
    for name in names:
        times: dict[int, list[float]] = {load: [] for load in loads}
        codes = set()
        for _ in range(args.repeats):  # alternated, so that drifts of the machine touch every condition alike
            for load in loads:
                with cpu_load(load):
                    seconds, code = stop_seconds(name, args.settle)
                times[load].append(seconds)
                codes.add(code)
        medians = {load: statistics.median(times[load]) for load in loads}
        within = "within" if max(max(values) for values in times.values()) < PROMISE_SECONDS else "NOT within"
        cells = " | ".join(f"{medians[load]:.2f} | {max(times[load]):.2f}" for load in loads)
        ratios = " | ".join(f"{medians[load] / medians[0]:.2f}" for load in loads if load)
        print(f"| {name} | {cells} | {ratios} | {sorted(codes)} ({within} {PROMISE_SECONDS:g} s) |")


if __name__ == "__main__":
    main()
