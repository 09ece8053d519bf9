"""Latency of one agent's action on one core: onnxruntime (the exported graph) against torch (the trained policy).

Two policies: the shipped MLP ``pretrained:ch5-bearing`` (a residual policy: its network, and the whole action with
the numpy controller added) and the thesis's recurrent actor (chapter 5: 512 dense -> 256 GRU -> 2, untrained: the
weights do not change the time), its state carried from call to call. torch runs on one thread
(``torch.set_num_threads(1)``), onnxruntime with ``intra_op_num_threads=1``. Each call acts for one agent's raw
observation (rows of a played episode); the median over ``--calls`` calls after ``--warm-up`` calls is printed, with
the date, the CPU (lscpu's model name) and the ratio torch / onnxruntime.

Usage: ``python benchmarks/onnx_latency.py [--calls 3000] [--note "machine shared with other work"]``
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import onnxruntime
import torch as th
from gymnasium import spaces

from sb3_formation.env.engine import FormationEngine
from sb3_formation.experiment.pretrained import ONNX_FILE, PRETRAINED_DIR, load_pretrained
from sb3_formation.runtime import OnnxPolicy
from sb3_formation.sb3.onnx_export import export_onnx
from sb3_formation.sb3.recurrent import RecurrentFormationPolicy
from sb3_formation.sb3.trained import TrainedPolicy
from sb3_formation.utils.machine import machine_line


def median_seconds(act: Callable[[np.ndarray], object], observations: np.ndarray, calls: int, warm_up: int) -> float:
    """Median seconds of ``act(row)`` over ``calls`` calls, cycling through the rows, after ``warm_up`` calls."""
    times = []
    for call in range(warm_up + calls):
        row = observations[call % len(observations)][None]
        start = time.perf_counter()
        act(row)
        times.append(time.perf_counter() - start)
    return statistics.median(times[warm_up:])


def episode_rows(policy: object, config: object, steps: int = 200) -> np.ndarray:
    """Agent 0's observations over ``steps`` steps of a stage-3 episode played by ``policy``."""
    engine = FormationEngine([config])
    observations, rows = engine.reset(0, seed=0), []
    for _ in range(steps):
        rows.append(observations[0])
        actions, _ = policy.predict(observations)
        observations = engine.step(np.asarray(actions, dtype=np.float64)).observations
    return np.stack(rows)


class Carried:
    """Calls a recurrent policy's ``predict`` with the state its previous call returned."""

    def __init__(self, policy: object) -> None:
        self.policy, self.state = policy, None

    def __call__(self, row: np.ndarray) -> None:
        _, self.state = self.policy.predict(row, self.state)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--calls", type=int, default=3000, help="timed calls per measurement (default 3000)")
    parser.add_argument("--warm-up", type=int, default=300, help="untimed calls first (default 300)")
    parser.add_argument("--note", default="", help="a line to print with the header (e.g. what else ran)")
    args = parser.parse_args()
    th.set_num_threads(1)
    print(f"onnx_latency: one agent's action, one core; {machine_line()}")
    print(f"  torch {th.__version__} (1 thread), onnxruntime {onnxruntime.__version__} (intra_op_num_threads 1)")
    if args.note:
        print(f"  note: {args.note}")
    print(f"  median of {args.calls} calls after {args.warm_up}")

    shipped = load_pretrained("ch5-bearing")
    exported = OnnxPolicy(PRETRAINED_DIR / "ch5-bearing" / ONNX_FILE, threads=1)
    rows = episode_rows(shipped, shipped.config.replace(stage=3))
    network = exported.session
    cases = [
        (
            "MLP network (ch5-bearing: normaliser + actor)",
            shipped.correction.predict,
            lambda row: network.run(None, {"observation": row}),
        ),
        (
            "MLP whole action (+ numpy controller)",
            shipped.predict,
            lambda row: exported.agent_step(row, np.zeros(1, int)).action,
        ),
    ]

    config = shipped.config
    size = rows.shape[1]
    box, actions = spaces.Box(-np.inf, np.inf, (size,), np.float32), spaces.Box(-1, 1, (2,), np.float32)
    recurrent = TrainedPolicy(
        RecurrentFormationPolicy(box, actions, lambda _: 3e-4), config, dict(shipped.correction.normalizer_state)
    )
    with tempfile.TemporaryDirectory() as folder:
        recurrent_onnx = OnnxPolicy(export_onnx(recurrent, Path(folder) / "gru.onnx"), threads=1)
        cases.append(("recurrent actor (512 dense -> 256 GRU, state carried)", Carried(recurrent), Carried(recurrent_onnx)))
        for label, torch_act, onnx_act in cases:
            torch_seconds = median_seconds(torch_act, rows, args.calls, args.warm_up)
            onnx_seconds = median_seconds(onnx_act, rows, args.calls, args.warm_up)
            print(
                f"  {label:<56} torch {torch_seconds * 1e6:8.1f} us   onnxruntime {onnx_seconds * 1e6:8.1f} us   "
                f"torch / onnxruntime {torch_seconds / onnx_seconds:5.2f}x"
            )


if __name__ == "__main__":
    main()
