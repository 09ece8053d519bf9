"""The policy contract: every kind of policy answers the team call (``predict``) and the agent call (``agent_step``) with
the same types, carries its state through both, routes its messages the same way, and refuses a task it does not fit
at ``fit`` with one line.

Kinds: a controller with memory, a residual policy on it, a trained MLP, a recurrent (GRU) and a talking (GRU with
messages) trained policy; the ONNX export of each learned one (run by the torch-free runtime); each of these behind the
safety filter (``safe:``).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_export import untrained
from test_messages import untrained as talking

from sb3_formation.controllers import ShrinkingController
from sb3_formation.controllers.base import AgentStep, Policy, TeamPolicy
from sb3_formation.controllers.residual import ResidualPolicy
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.engine import FormationEngine
from sb3_formation.env.geometry import ring_rows
from sb3_formation.env.observations import observation_fields, observation_layout
from sb3_formation.runtime import OnnxPolicy, load_onnx_policy
from sb3_formation.safety.policy import SafePolicy
from sb3_formation.sb3.onnx_export import export_onnx

CONFIG = FormationConfig.task("ch5-bearing", stage=3)
#: the largest difference between a team call and the agent calls of its rows (ONNX runs a batch of one row otherwise)
TOLERANCE = 1e-5
TEAMS, N = 2, CONFIG.n_agents

LEARNED: dict[str, Callable[[], Policy]] = {
    "residual": lambda: ResidualPolicy(ShrinkingController(CONFIG), untrained(CONFIG, None, seed=3), 0.3),
    "trained": lambda: untrained(CONFIG, None, seed=1),
    "recurrent": lambda: untrained(CONFIG, "gru", seed=2),
    "talking": lambda: talking(CONFIG, True, seed=4),
}
KINDS = ["controller", *LEARNED, *(f"onnx:{kind}" for kind in LEARNED)]
KINDS += [f"safe:{kind}" for kind in KINDS]
#: kinds whose agents carry a state from step to step, and those that send messages
WITH_MEMORY = {"controller", "residual", "recurrent", "talking"}
TALKING = {"talking"}


def build(kind: str, folder: Path) -> TeamPolicy:
    """The policy of a kind (an ONNX one exported into ``folder``)."""
    if kind.startswith("safe:"):
        return SafePolicy(build(kind.removeprefix("safe:"), folder))
    if kind.startswith("onnx:"):
        learned = LEARNED[kind.removeprefix("onnx:")]()
        return load_onnx_policy(export_onnx(learned, folder / f"{kind.removeprefix('onnx:')}.onnx"), threads=1)
    return ShrinkingController(CONFIG) if kind == "controller" else LEARNED[kind]()


def base_kind(kind: str) -> str:
    return kind.removeprefix("safe:").removeprefix("onnx:")


def played_rows(steps: int) -> list[np.ndarray]:
    """Observations of two teams of 6 over ``steps`` steps of the shrinking controller (a stage-3 episode each)."""
    engine, controller = FormationEngine([CONFIG] * TEAMS), ShrinkingController(CONFIG)
    rows, state = [np.concatenate([engine.reset(team, seed=team) for team in range(TEAMS)])], None
    for _ in range(steps - 1):
        actions, state = controller.predict(rows[-1], state)
        rows.append(engine.step(actions.astype(np.float64)).observations)
    return rows


ROWS = played_rows(4)


@pytest.mark.parametrize("kind", KINDS)
def test_every_kind_answers_both_calls_with_the_same_types_state_and_messages(kind: str, tmp_path: Path) -> None:
    """Four steps of two teams through ``predict``, and each agent of both teams through ``agent_step`` alone with its
    own state and the messages its ring neighbours sent it (routed by hand): the same actions, and the same messages."""
    policy = build(kind, tmp_path)
    assert isinstance(policy, TeamPolicy) and isinstance(policy, Policy)
    size = 4 if base_kind(kind) in TALKING else 0
    assert policy.message_size == size
    team_state: Any = None
    agent_states: list[Any] = [None] * (TEAMS * N)
    sent = np.zeros((TEAMS * N, size), np.float32)
    neighbours = ring_rows([N] * TEAMS)
    for step, rows in enumerate(ROWS):
        starts = np.full(TEAMS * N, step == 0)
        actions, team_state = policy.predict(rows, team_state, starts)
        assert actions.shape == (TEAMS * N, 2) and actions.dtype == np.float32
        assert np.isfinite(actions).all() and np.abs(actions).max() <= 1.0
        heard = np.zeros((TEAMS * N, 2, size), np.float32) if step == 0 else sent[neighbours]
        for row in range(TEAMS * N):
            received = heard[row][None] if size else None
            result = policy.agent_step(rows[[row]], np.array([row % N]), agent_states[row], starts[[row]], received)
            assert isinstance(result, AgentStep)
            assert result.action.shape == (1, 2) and result.action.dtype == np.float32
            assert result.message.shape == (1, size) and result.message.dtype == np.float32
            assert np.abs(result.action[0] - actions[row]).max() <= TOLERANCE, (step, row)
            agent_states[row] = result.state
            sent[row] = result.message[0]
        if size:  # the team call's state is (the agents' state, the messages they sent): the same messages
            assert np.abs(team_state[1] - sent).max() <= TOLERANCE
    if size:
        assert np.abs(sent).max() > 0.1  # messages were sent, not zeros


@pytest.mark.parametrize("kind", KINDS)
def test_the_state_round_trips_and_an_episode_start_resets_it(kind: str, tmp_path: Path) -> None:
    """A state handed back changes the actions of a policy with memory (and of no other), and ``episode_start`` makes
    them the actions of a fresh start (state ``None``)."""
    policy = build(kind, tmp_path)
    state: Any = None
    for rows in ROWS[:-1]:
        _, state = policy.predict(rows, state)
    carried, _ = policy.predict(ROWS[-1], state)
    fresh, _ = policy.predict(ROWS[-1])
    restarted, _ = policy.predict(ROWS[-1], state, np.ones(TEAMS * N, dtype=bool))
    np.testing.assert_array_equal(restarted, fresh)
    assert (np.abs(carried - fresh).max() > 1e-4) == (base_kind(kind) in WITH_MEMORY)


@pytest.mark.parametrize("kind", [kind for kind in KINDS if base_kind(kind) != "controller"])
def test_a_learned_policy_refuses_a_task_it_does_not_fit_at_fit_in_one_line(kind: str, tmp_path: Path) -> None:
    """Other lidar rays, another team size (trained on one), another dynamics: each named in one line, for every kind
    and its ONNX export, behind the filter or not. A holonomic export on a unicycle task is refused at fit."""
    policy = build(kind, tmp_path)
    for change, named in (
        ({"lidar_rays": 45}, "lidar_rays=90 in the model, 45 in the env"),
        ({"n_agents": 4}, "n_agents=6 in the model, 4 in the env"),
        ({"dynamics": "unicycle"}, "dynamics='holonomic' in the model, 'unicycle' in the env"),
    ):
        with pytest.raises(ValueError, match="does not fit this env") as error:
            policy.fit(CONFIG.replace(**change))
        assert named in str(error.value) and "\n" not in str(error.value)
    assert policy.fit(CONFIG) is policy


def test_a_controller_fits_every_task_and_acts_through_its_dynamics() -> None:
    """A controller reads its fields by name and acts through the task's dynamics: it fits a unicycle task, 45 rays and
    a team of 4, and acts there."""
    config = CONFIG.replace(dynamics="unicycle", lidar_rays=45, n_agents=4)
    fitted = ShrinkingController(CONFIG).fit(config)
    engine = FormationEngine([config])
    actions, _ = fitted.predict(engine.reset(0, seed=0))
    assert actions.shape == (4, 2) and np.isfinite(actions).all()


def test_an_export_trained_behind_the_filter_loads_behind_it_and_never_filters_itself(tmp_path: Path) -> None:
    """``load_onnx_policy`` puts a shielded export behind :class:`SafePolicy` with the gains its metadata record; the
    :class:`OnnxPolicy` inside returns the unfiltered actions, which differ where the filter acts."""
    shielded = SafePolicy(untrained(CONFIG, None, seed=1))
    loaded = load_onnx_policy(export_onnx(shielded, tmp_path / "shielded.onnx"), threads=1)
    assert isinstance(loaded, SafePolicy) and isinstance(loaded.policy, OnnxPolicy)
    assert loaded.filter.gains == shielded.filter.gains
    rows = ROWS[0].copy()
    rows[:, observation_layout(observation_fields(CONFIG))["lidar_obstacles"]] = 0.005  # walls 7.5 mm away all round
    filtered, _ = loaded.predict(rows)
    unfiltered, _ = loaded.policy.predict(rows)
    expected, _ = shielded.predict(rows)
    assert np.abs(filtered - expected).max() <= TOLERANCE
    assert np.abs(filtered - unfiltered).max() > 0.01


def one_line_error(call: Callable[[], object], match: str) -> None:
    with pytest.raises(ValueError, match=match) as error:
        call()
    assert "\n" not in str(error.value)


@pytest.mark.parametrize("kind", KINDS)
def test_non_finite_or_misshapen_inputs_are_refused_in_one_line_by_every_kind(kind: str, tmp_path: Path) -> None:
    """A NaN or infinite observation, rows of the wrong width, agent indices that do not match the rows, a state with
    a NaN or of the wrong kind, and non-finite received messages: each a one-line ValueError, in both calls, never NaN
    actions."""
    policy = build(kind, tmp_path)
    rows = ROWS[1].copy()
    for bad in (np.nan, np.inf, -np.inf):
        spoilt = rows.copy()
        spoilt[4, 3] = bad
        one_line_error(lambda spoilt=spoilt: policy.predict(spoilt), "observations hold NaN or infinite values")
        one_line_error(lambda spoilt=spoilt: policy.agent_step(spoilt[[4]], np.array([4])), "NaN or infinite")
    one_line_error(lambda: policy.predict(rows[:, :-1]), "features per agent")
    one_line_error(lambda: policy.agent_step(rows[:2], np.array([0])), "2 observation rows")
    _, state = policy.predict(rows)
    if base_kind(kind) in WITH_MEMORY:
        spoilt_state = nan_filled(state)
        one_line_error(lambda: policy.predict(rows, spoilt_state), "state holds NaN or infinite values")
        one_line_error(lambda: policy.predict(rows, 5), "state")
        one_line_error(lambda: policy.predict(rows, ("a", "b", "c")), "state")
    if base_kind(kind) in TALKING:
        heard = np.full((1, 2, 4), np.nan)
        one_line_error(lambda: policy.agent_step(rows[[0]], np.array([0]), received=heard), "NaN or infinite")
    else:
        one_line_error(lambda: policy.agent_step(rows[[0]], np.array([0]), received=np.zeros((1, 2, 4))), "send no messages")


def nan_filled(state: Any) -> Any:
    """The same structure as a policy's state, every number NaN."""
    if state is None:
        return None
    if isinstance(state, tuple | list):
        return type(state)(nan_filled(part) for part in state)
    return np.full(np.shape(state), np.nan)
