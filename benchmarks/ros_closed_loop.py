"""A shipped policy flown over ROS 2 in closed loop against ``sb3-formation evaluate`` on the same seeds.

The simulator node and the team's agent nodes run as a user starts them, in two processes
(``python -m sb3_formation.ros sim MODEL --mode sync ... --out FILE`` and ``python -m sb3_formation.ros agents MODEL
--mode sync``), with the safety filter on. The same episodes (episode k from ``reset(seed=SEED + k)``) are evaluated
in process twice: the trained policy behind the filter (``safe:pretrained:<name>``, torch, what ``sb3-formation
evaluate safe:pretrained:<name>`` plays) for the successes, and its exported file behind the filter (``safe:onnx:``, the
graph the nodes run) for the trajectories. Printed per episode: the outcome and steps of each, and the largest distance
(m) between an agent's position over ROS 2 and in process over the steps both played; then the totals, the wall time
and the machine.

The scanner of the simulator node sees what a real one sees: a teammate hides what lies behind it, which the
simulator's lidar does not (``docs/deployment.md``). The episodes where no obstacle stood behind a teammate agree to
float32 rounding; the others drift apart from the first such step.

With ``--disturbances NAME|FILE`` the episodes meet those disturbances on both sides: the simulator node applies them
(``ros sim --disturbances``: noisy odometry and scans, delivered late, motor errors and action delays in its engine),
the agents' filters declare their bounds from them (``ros agents --filter-disturbances``), and the in-process
evaluations play them (``evaluate``'s ``disturbances`` override). The same seeds draw the same noise on both sides; the
trajectories part where the nodes' rows differ from the engine's (see ``docs/deployment.md``), so the measure is the
outcome: the same success or failure, and a length within ``--length-tolerance`` of evaluation's.

Usage (in the ROS environment): ``.venv-ros/bin/python benchmarks/ros_closed_loop.py [--policy ch5-bearing]
[--scenes passage] [--episodes 20] [--seed 0] [--see-through-agents] [--disturbances realistic] [--domain-id 33]
[--out FILE]`` (``--see-through-agents``: the simulator's scans see through the agents, as its own lidar does, which
leaves only the nodes' arithmetic between the two)
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from sb3_formation.env.disturbances import load_disturbances
from sb3_formation.experiment.evaluation import evaluate
from sb3_formation.experiment.pretrained import ONNX_FILE, pretrained_folder
from sb3_formation.experiment.targets import load_policy
from sb3_formation.utils.machine import machine_line

#: (s) the agents' input_timeout: longer than any pause of a loaded machine
LOCKSTEP_TIMEOUT = 60.0


def ros_episodes(model: Path, args: argparse.Namespace, folder: Path) -> tuple[dict[str, np.ndarray], float]:
    """The episodes flown over ROS 2 (the simulator node's ``--out`` file) and the wall time (s) they took."""
    environment = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": str(args.domain_id)}
    out = folder / "ros.npz"
    sim = [sys.executable, "-m", "sb3_formation.ros", "sim", str(model), "--stage", "3", "--seed", str(args.seed)]
    sim += ["--episodes", str(args.episodes), "--mode", "sync", "--out", str(out)]
    sim += ["--scenes", args.scenes] if args.scenes else []
    sim += ["--see-through-agents"] if args.see_through_agents else []
    agents = [sys.executable, "-m", "sb3_formation.ros", "agents", str(model), "--mode", "sync"]
    if args.disturbances != "ideal":
        sim += ["--disturbances", args.disturbances]
        agents += ["--filter-disturbances", args.disturbances]
    # the lockstep must hold on a loaded machine: a simulator starved of the CPU for input_timeout would get the
    # agents' watchdog zeros as a step's commands (docs/deployment.md)
    agents += ["--ros-args", "-p", f"input_timeout:={LOCKSTEP_TIMEOUT}"]
    start = time.perf_counter()
    with open(folder / "agents.log", "w") as log:
        team = subprocess.Popen(agents, env=environment, stdout=log, stderr=subprocess.STDOUT)
        try:
            subprocess.run(sim, env=environment, check=True, stdout=subprocess.DEVNULL)
        finally:
            team.terminate()
            team.wait(timeout=30)
    seconds = time.perf_counter() - start
    with np.load(out) as data:
        return {key: data[key] for key in data.files}, seconds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", default="ch5-bearing", help="a shipped policy's name")
    parser.add_argument("--scenes", default="", help="the scenes (default: the policy's)")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--domain-id", type=int, default=33)
    parser.add_argument("--see-through-agents", action="store_true", help="scans that see through the agents")
    parser.add_argument("--disturbances", default="ideal", help="a profile (ideal, realistic, harsh) or a YAML file")
    parser.add_argument(
        "--length-tolerance", type=float, default=0.1, help="a length within this share of evaluation's is the same"
    )
    parser.add_argument("--note", default="")
    parser.add_argument("--out", type=Path, default=None, help="also write the output to this file")
    args = parser.parse_args()
    model = pretrained_folder(args.policy) / ONNX_FILE
    overrides: dict = {"scenes": args.scenes} if args.scenes else {}
    if args.disturbances != "ideal":
        overrides["disturbances"] = load_disturbances(args.disturbances)
    protocol = {"episodes": args.episodes, "stage": 3, "seed": args.seed, "env_overrides": overrides}
    trained = evaluate(load_policy(f"safe:pretrained:{args.policy}"), record=0, **protocol)
    exported = evaluate(load_policy(f"safe:onnx:{model}"), record=min(args.episodes, 100), **protocol)
    with tempfile.TemporaryDirectory() as folder:
        flown, seconds = ros_episodes(model, args, Path(folder))
    lines = [
        f"ros_closed_loop: {machine_line()}" + (f"; {args.note}" if args.note else ""),
        f"  pretrained:{args.policy}, scenes {args.scenes or exported.scenes}, stage 3, seeds {args.seed}-"
        f"{args.seed + args.episodes - 1}, safety filter on; simulator and agent nodes in sync mode, two processes; "
        + ("scans see through the agents" if args.see_through_agents else "agents stop the scans' beams (a real scanner)")
        + ("" if args.disturbances == "ideal" else f"; disturbances {args.disturbances} on both sides"),
        "  seed  evaluate (torch)   evaluate (onnx)    over ROS 2         largest position difference to onnx (m)",
    ]
    deviations = []
    for k, (row, onnx_row) in enumerate(zip(trained.episodes, exported.episodes)):
        steps = int(flown["steps"][k])
        common = min(steps, int(onnx_row["length"])) + 1
        positions = flown[f"positions_{k}"][:common]
        deviation = float(np.linalg.norm(positions - exported.trajectories.positions[k, :common], axis=-1).max())
        deviations.append(deviation)
        cells = [
            f"{'success' if outcome else 'failure'} {count:5d}"
            for outcome, count in (
                (row["success"], row["length"]),
                (onnx_row["success"], onnx_row["length"]),
                (bool(flown["success"][k]), steps),
            )
        ]
        lines.append(f"  {args.seed + k:4d}  {cells[0]:18s} {cells[1]:18s} {cells[2]:18s} {deviation:.2e}")
    successes = [sum(bool(row["success"]) for row in rows) for rows in (trained.episodes, exported.episodes)]
    same = [
        sum(bool(row["success"]) == bool(flown["success"][k]) for k, row in enumerate(rows))
        for rows in (trained.episodes, exported.episodes)
    ]
    alike = [
        sum(
            bool(row["success"]) == bool(flown["success"][k])
            and abs(int(flown["steps"][k]) - int(row["length"])) <= args.length_tolerance * int(row["length"])
            for k, row in enumerate(rows)
        )
        for rows in (trained.episodes, exported.episodes)
    ]
    lines += [
        f"  successes: evaluate (torch) {successes[0]}/{args.episodes}, evaluate (onnx) {successes[1]}/{args.episodes}, "
        f"over ROS 2 {int(flown['success'].sum())}/{args.episodes}; "
        f"same outcome as evaluate (torch) in {same[0]}/{args.episodes}, as evaluate (onnx) in {same[1]}/{args.episodes}",
        f"  same outcome and length within {args.length_tolerance:.0%}: as evaluate (torch) in {alike[0]}/{args.episodes}, "
        f"as evaluate (onnx) in {alike[1]}/{args.episodes}",
        f"  largest position difference: median {np.median(deviations):.2e} m, max {max(deviations):.2e} m; "
        f"episodes within 1e-6 m: {sum(d <= 1e-6 for d in deviations)}/{args.episodes}",
        f"  wall time over ROS 2: {seconds:.0f} s ({seconds / int(flown['steps'].sum()) * 1e3:.1f} ms a step)",
    ]
    text = "\n".join(lines)
    print(text)
    if args.out is not None:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
