"""Gradient work of one recurrent minibatch against the length of its sequences (why max_sequence_length is 16).

One minibatch of 512 steps of the thesis's recurrent networks (ch5, 211 observation values) is forward, backward and
Adam-stepped as 512 / L sequences of L steps, for L = 128 (a whole rollout) down to 8. Prints the median time per
minibatch and its ratio to L = 128, for GRU and LSTM cells.

Usage: ``python benchmarks/sequence_length.py [--repeats 5]``
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch as th
from gymnasium import spaces

from sb3_formation.sb3.recurrent import RecurrentFormationPolicy

LENGTHS = (128, 32, 20, 16, 8)


def minibatch_seconds(policy: RecurrentFormationPolicy, length: int, repeats: int) -> float:
    """Median seconds of forward + backward + Adam over one 512-step minibatch of ``length``-step sequences."""
    batch = 512 // length
    observations, actions = th.randn(length, batch, 211), th.zeros(length, batch, 2)
    times = []
    for _ in range(repeats + 1):
        start = time.perf_counter()
        values, log_prob, _ = policy.evaluate_sequences(observations, actions, policy.initial_state(batch))
        loss = values.square().mean() - log_prob.mean()
        policy.optimizer.zero_grad()
        loss.backward()
        policy.optimizer.step()
        times.append(time.perf_counter() - start)
    return statistics.median(times[1:])  # the first call warms up


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    observation_space = spaces.Box(-1.0, 1.0, (211,), np.float32)
    action_space = spaces.Box(-1.0, 1.0, (2,), np.float32)
    print(f"one 512-step minibatch of the thesis's recurrent networks; torch threads {th.get_num_threads()}")
    for cell in ("gru", "lstm"):
        policy = RecurrentFormationPolicy(observation_space, action_space, lambda _: 5e-5, cell=cell)
        reference = None
        for length in LENGTHS:
            seconds = minibatch_seconds(policy, length, args.repeats)
            reference = reference or seconds
            print(
                f"  {cell:<4} {512 // length:3d} sequences of {length:3d} steps: {seconds * 1000:6.1f} ms "
                f"({seconds / reference:.2f}x of 128-step sequences)"
            )


if __name__ == "__main__":
    main()
