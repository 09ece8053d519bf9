"""The stepping engine reproduces the golden trajectories recorded before it was written (``tests/engine_goldens.py``):
every task, team sizes 3 to 16 in one VecEnv, 1 to 3 processes, terminal observations, stage changes, the PettingZoo
env's resets and state, and evaluations, bit for bit."""

from __future__ import annotations

import json

import pytest
from engine_goldens import GOLDENS, case_name, cases

from sb3_formation.experiment.pretrained import numerics_fingerprint

CASES = dict(cases())


def golden(name: str) -> list[str]:
    data = json.loads(GOLDENS.read_text())
    recorded = data["by_numerics"].get(numerics_fingerprint())
    if recorded is None:  # pragma: no cover - another CPU
        pytest.skip(
            f"no goldens for this CPU's float kernels; record them from {data['recorded_from'][:7]} (see "
            "tests/engine_goldens.py)"
        )
    return recorded[case_name(name)]


@pytest.mark.parametrize("name", list(CASES))
def test_the_engine_reproduces_the_golden_trajectories(name: str) -> None:
    expected = golden(name)
    played = CASES[name]()
    first = next((step for step, (a, b) in enumerate(zip(played, expected)) if a != b), None)
    assert first is None and len(played) == len(expected), f"{name}: first different digest at step {first}"
