"""FormationConfig: the thesis tasks (Tables 4.1 and 5.1), derived values, validation and per-stage coefficients."""

from __future__ import annotations

import dataclasses
import math
import re
from typing import Any

import numpy as np
import pymunk
import pytest

from sb3_formation.env.config import COLLISION_BIAS, MAX_SUBSTEPS, MAX_WORLD_SIZE, FormationConfig

TASK_NAMES = ("ch4-individual", "ch4-team", "ch5-angle", "ch5-bearing")

#: Table 4.1 (K_ref -> k_dist, m_ref -> m_dist, beta^f = 60 deg); n = 3 (thesis 4.2).
TABLE_4_1: dict[str, Any] = {
    "k_goal": 0.5,
    "k_dist": 2.0,
    "k_angle": 0.4,
    "k_move": 2.0,
    "k_coll": 1.0,
    "r_reached": 9.0,
    "eta_g": 0.5,
    "m_ang_deg": 30.0,
    "d_ref": 2.4,
    "d_comm": 3.0,
    "m_dist": 0.1,
    "r_o": -6.0,
    "r_j": -1.0,
    "d_safe": 0.02,
    "n_agents": 3,
    "chapter": "ch4",
}

#: Table 5.1; n = 6 (thesis 5.2).
TABLE_5_1: dict[str, Any] = {
    "k_goal": 0.5,
    "k_dist": 1.0,
    "k_move": 0.3,
    "k_velocity": 0.1,
    "k_coll": 0.5,
    "r_c": 0.01,
    "r_reached": 4.0,
    "r_late": -10.0,
    "eta_g": 0.4,
    "eta_c": 1.2,
    "m_ang_deg": 30.0,
    "d_ref": 1.5,
    "d_comm": 3.0,
    "m_dist": 0.1,
    "k1": -1.1,
    "r_o": -5.0,
    "r_j": -1.0,
    "d_safe": 0.05,
    "n_agents": 6,
    "chapter": "ch5",
}

EXPECTED_TASKS: dict[str, dict[str, Any]] = {
    "ch4-individual": {**TABLE_4_1, "team_reward": False},
    "ch4-team": {**TABLE_4_1, "team_reward": True},
    "ch5-angle": {**TABLE_5_1, "k_angle": 0.3, "k_bearing": 0.0, "team_reward": False},  # thesis 5.3, Policy 1
    "ch5-bearing": {**TABLE_5_1, "k_angle": 0.0, "k_bearing": 0.3, "team_reward": False},  # thesis 5.3, Policy 2
}

#: Shared by both chapters: thesis 4.3 / 5.3 (R_a = 0.2 m, v_max = 0.05 m/s, dt = 0.3 s, 15 m x 10 m, b x d = 90 rays,
#: range 1.5 m, T_s = 2500, rewards clipped to [-10, 10]).
COMMON: dict[str, Any] = {
    "agent_radius": 0.2,
    "v_max": 0.05,
    "dt": 0.3,
    "world_width": 15.0,
    "world_height": 10.0,
    "lidar_rays": 90,
    "lidar_range": 1.5,
    "max_steps": 2500,
    "reward_clip": 10.0,
}


def _assert_values(config: FormationConfig, expected: dict[str, Any]) -> None:
    for name, value in expected.items():
        actual = getattr(config, name)
        if isinstance(value, (bool, str, int)) and not isinstance(value, float):
            assert actual == value and type(actual) is type(value), f"{name}: {actual!r} != {value!r}"
        else:
            assert actual == pytest.approx(value, rel=1e-12, abs=1e-15), f"{name}: {actual!r} != {value!r}"


# Tasks ------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", TASK_NAMES)
def test_task_carries_table_values(name: str) -> None:
    """Each task carries its chapter's table values and the shared team specifications."""
    config = FormationConfig.task(name)
    _assert_values(config, EXPECTED_TASKS[name])
    _assert_values(config, COMMON)


def test_ch4_uses_k1_from_table_5_1() -> None:
    """Chapter 4 uses k_1 but Table 4.1 omits it: it comes from Table 5.1 (docs/design.md "Rewards")."""
    assert FormationConfig.task("ch4-individual").k1 == pytest.approx(-1.1)
    assert FormationConfig.task("ch4-team").k1 == pytest.approx(-1.1)


def test_only_ch4_team_has_team_reward() -> None:
    """team_reward is True for ch4-team and False for the three others."""
    flags = {name: FormationConfig.task(name).team_reward for name in TASK_NAMES}
    assert flags == {"ch4-individual": False, "ch4-team": True, "ch5-angle": False, "ch5-bearing": False}


@pytest.mark.parametrize(
    ("name", "beta"),
    [("ch4-individual", 60.0), ("ch4-team", 60.0), ("ch5-angle", 120.0), ("ch5-bearing", 120.0)],
)
def test_beta_ref_of_tasks(name: str, beta: float) -> None:
    """beta^f = 60 deg for n = 3 (Table 4.1), beta^ref = 120 deg for n = 6 (Table 5.1)."""
    assert FormationConfig.task(name).beta_ref_deg == pytest.approx(beta, abs=1e-12)


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        ({}, 1.0 * 0.05 / 0.3),  # m * v_max / dt = 1 * 0.05 / 0.3 = 1/6 N
        ({"agent_mass": 2.0, "v_max": 0.1, "dt": 0.5}, 0.4),  # 2 * 0.1 / 0.5 = 0.4 N
        ({"agent_mass": 3.0}, 0.5),  # 3 * 0.05 / 0.3 = 0.5 N
        ({"max_force": 2.5}, 2.5),  # explicit F_max wins
    ],
)
def test_force_max(overrides: dict[str, Any], expected: float) -> None:
    """force_max is m * v_max / dt unless max_force is set."""
    config = FormationConfig.task("ch5-bearing", **overrides)
    assert config.force_max == pytest.approx(expected, rel=1e-12)


def test_force_max_default_is_one_sixth_newton() -> None:
    """The thesis numbers give F_max = 1 kg * 0.05 m/s / 0.3 s = 1/6 N for every task."""
    for name in TASK_NAMES:
        assert FormationConfig.task(name).force_max == pytest.approx(1 / 6, rel=1e-12)


# n_agents -----------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", TASK_NAMES)
@pytest.mark.parametrize(("n_agents", "beta"), [(3, 60.0), (4, 90.0), (5, 108.0), (8, 135.0)])
def test_any_team_size_with_any_task(name: str, n_agents: int, beta: float) -> None:
    """n >= 3 works with every task; beta^ref is the n-gon's interior angle (n - 2) * 180 / n."""
    config = FormationConfig.task(name, n_agents=n_agents)
    assert config.n_agents == n_agents
    assert config.beta_ref_deg == pytest.approx(beta, abs=1e-12)
    # the starting n-gon fits: sides below d_ref, vertices within eta_c of the centroid, agents not overlapping
    assert config.start_circumradius <= config.eta_c + 1e-12
    assert 2 * config.agent_radius < config.start_side_length < config.d_ref
    # the other task values are untouched by the override
    expected = {key: value for key, value in EXPECTED_TASKS[name].items() if key != "n_agents"}
    _assert_values(config, expected)


@pytest.mark.parametrize("name", TASK_NAMES)
def test_two_agents_rejected(name: str) -> None:
    """n_agents = 2 raises a ValueError naming n_agents and the bound >= 3."""
    with pytest.raises(ValueError, match=r"n_agents") as info:
        FormationConfig.task(name, n_agents=2)
    assert ">= 3" in str(info.value)


def test_two_agents_rejected_without_task() -> None:
    """The bound holds for a directly built config too."""
    with pytest.raises(ValueError, match=r"n_agents.*>= 3"):
        FormationConfig(n_agents=2)


# Validation -------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("overrides", "field", "allowed"),
    [
        ({"v_max": 0.0}, "v_max", r"> ?0|positive"),
        ({"v_max": float("nan")}, "v_max", r"> ?0|positive"),
        ({"dt": -1.0}, "dt", r"> ?0|positive"),
        ({"agent_radius": -0.2}, "agent_radius", r"> ?0|positive"),
        ({"stage": 4}, "stage", r"1, 2,? or 3|\{1, 2, 3\}|\[1, 3\]|1 to 3|1\.\.3"),
        ({"stage": 0}, "stage", r"1, 2,? or 3|\{1, 2, 3\}|\[1, 3\]|1 to 3|1\.\.3"),
        ({"lidar_rays": 0}, "lidar_rays", r">= ?1|> ?0|positive"),
        ({"formation_scale": 1.5}, "formation_scale", r"\(0, 1\)|0 < .*< 1"),
        ({"formation_scale": 0.0}, "formation_scale", r"\(0, 1\)|0 < .*< 1"),
        ({"chapter": "ch9"}, "chapter", r"ch4.*ch5"),
        ({"n_agents": True}, "n_agents", r">= ?3"),
        ({"n_agents": 3.0}, "n_agents", r">= ?3"),
        ({"d_safe": -0.01}, "d_safe", r">= ?0"),
    ],
)
def test_invalid_field_named_with_range(overrides: dict[str, Any], field: str, allowed: str) -> None:
    """An invalid value raises a ValueError naming the field and its allowed range."""
    with pytest.raises(ValueError) as info:
        FormationConfig.task("ch5-bearing", **overrides)
    message = str(info.value)
    assert re.search(rf"\b{field}\b", message), message
    assert re.search(allowed, message), message


@pytest.mark.parametrize("d_comm", [1.0, 1.5])  # below and equal to d_ref = 1.5 (need d_ref < d_comm, thesis 3.1.3)
def test_d_comm_must_exceed_d_ref(d_comm: float) -> None:
    """d_comm <= d_ref raises a ValueError naming both."""
    with pytest.raises(ValueError) as info:
        FormationConfig.task("ch5-bearing", d_comm=d_comm)
    assert "d_comm" in str(info.value) and "d_ref" in str(info.value)


def test_unknown_disabled_term_named() -> None:
    """stage_disabled_terms with an unknown term names the field and the term."""
    with pytest.raises(ValueError) as info:
        FormationConfig.task("ch5-bearing", stage_disabled_terms=(("angle", "teleport"), (), ()))
    message = str(info.value)
    assert "stage_disabled_terms" in message and "teleport" in message


def test_disabled_terms_need_three_stages() -> None:
    """stage_disabled_terms must give one entry per stage."""
    with pytest.raises(ValueError, match="stage_disabled_terms"):
        FormationConfig.task("ch5-bearing", stage_disabled_terms=(("angle",), ()))


def test_unknown_task_lists_valid_tasks() -> None:
    """task('nope') raises a ValueError listing the valid tasks."""
    with pytest.raises(ValueError) as info:
        FormationConfig.task("nope")
    message = str(info.value)
    assert "nope" in message
    for name in TASK_NAMES:
        assert name in message


def test_unknown_override_named_with_valid_fields() -> None:
    """task(name, bogus=1) raises a ValueError naming 'bogus' and listing the valid fields."""
    with pytest.raises(ValueError) as info:
        FormationConfig.task("ch5-bearing", bogus=1)
    message = str(info.value)
    assert "bogus" in message
    for field in ("n_agents", "v_max", "d_ref", "stage_disabled_terms", "placement_clearance"):
        assert field in message


def test_replace_validates() -> None:
    """replace() applies changes, leaves the original alone and validates like a new config."""
    config = FormationConfig.task("ch5-bearing")
    changed = config.replace(stage=3, n_agents=4)
    assert (changed.stage, changed.n_agents) == (3, 4)
    assert (config.stage, config.n_agents) == (1, 6)
    with pytest.raises(ValueError, match=r"\bv_max\b"):
        config.replace(v_max=0.0)
    with pytest.raises(ValueError, match=r"n_agents"):
        config.replace(n_agents=2)
    with pytest.raises(ValueError, match=r"d_comm"):
        config.replace(d_comm=1.0)
    with pytest.raises(ValueError, match="bogus"):
        config.replace(bogus=1)


def test_config_is_frozen() -> None:
    """Fields cannot be assigned after construction."""
    config = FormationConfig.task("ch4-individual")
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.v_max = 1.0  # type: ignore[misc]
    assert config.v_max == 0.05


def test_config_hashable_and_equal_by_value() -> None:
    """Two configs from the same task are equal; a different stage is not."""
    first = FormationConfig.task("ch5-angle")
    assert first == FormationConfig.task("ch5-angle")
    assert hash(first) == hash(FormationConfig.task("ch5-angle"))
    assert first != first.replace(stage=2)


# Reward coefficients per stage ------------------------------------------------------------------------------------

_CH4_ALL = {
    "time": 0.0,
    "angle": 0.4,
    "bearing": 0.0,
    "dist": 2.0,
    "centroid": 0.0,
    "goal": 0.5,
    "move": 2.0,
    "velocity": 0.0,
    "coll": 1.0,
}
_CH5_STAGE3 = {"time": 1.0, "dist": 1.0, "centroid": 1.0, "goal": 0.5, "move": 0.3, "velocity": 0.1, "coll": 0.5}

EXPECTED_COEFFICIENTS: dict[str, dict[int, dict[str, float]]] = {
    # chapter 4 (eq. 26): phase 1 has no angle requirement, phases 2 and 3 have every term (thesis 4.3)
    "ch4-individual": {1: {**_CH4_ALL, "angle": 0.0}, 2: _CH4_ALL, 3: _CH4_ALL},
    "ch4-team": {1: {**_CH4_ALL, "angle": 0.0}, 2: _CH4_ALL, 3: _CH4_ALL},
    # chapter 5 (eq. 42): stage 1 no neighbour distance nor shape, stage 2 + distance, stage 3 + shape
    # (docs/design.md "Curriculum placements")
    "ch5-angle": {
        1: {**_CH5_STAGE3, "dist": 0.0, "angle": 0.0, "bearing": 0.0},
        2: {**_CH5_STAGE3, "angle": 0.0, "bearing": 0.0},
        3: {**_CH5_STAGE3, "angle": 0.3, "bearing": 0.0},
    },
    "ch5-bearing": {
        1: {**_CH5_STAGE3, "dist": 0.0, "angle": 0.0, "bearing": 0.0},
        2: {**_CH5_STAGE3, "angle": 0.0, "bearing": 0.0},
        3: {**_CH5_STAGE3, "angle": 0.0, "bearing": 0.3},
    },
}


@pytest.mark.parametrize("name", TASK_NAMES)
@pytest.mark.parametrize("stage", [1, 2, 3])
def test_reward_coefficients_per_stage(name: str, stage: int) -> None:
    """reward_coefficients(stage) gives every term's coefficient with the stage's disabled terms at 0."""
    expected = EXPECTED_COEFFICIENTS[name][stage]
    coefficients = FormationConfig.task(name).reward_coefficients(stage)
    assert set(coefficients) == {"time", "angle", "bearing", "dist", "centroid", "goal", "move", "velocity", "coll"}
    assert coefficients == pytest.approx(expected, abs=1e-12)


@pytest.mark.parametrize("name", TASK_NAMES)
@pytest.mark.parametrize("stage", [1, 2, 3])
def test_reward_coefficients_default_to_config_stage(name: str, stage: int) -> None:
    """Without an argument, reward_coefficients uses config.stage."""
    config = FormationConfig.task(name, stage=stage)
    assert config.reward_coefficients() == pytest.approx(EXPECTED_COEFFICIENTS[name][stage], abs=1e-12)


def test_custom_disabled_terms_respected() -> None:
    """A custom stage_disabled_terms switches off exactly the listed terms."""
    config = FormationConfig.task("ch5-bearing", stage_disabled_terms=(("goal", "coll"), ("move",), ()))
    assert config.reward_coefficients(1)["goal"] == 0.0
    assert config.reward_coefficients(1)["coll"] == 0.0
    assert config.reward_coefficients(1)["dist"] == pytest.approx(1.0)
    assert config.reward_coefficients(2)["move"] == 0.0
    assert config.reward_coefficients(2)["goal"] == pytest.approx(0.5)
    assert config.reward_coefficients(3)["bearing"] == pytest.approx(0.3)


def test_stage_arguments_are_validated_and_numpy_integers_accepted() -> None:
    config = FormationConfig.task("ch5-bearing")
    for stage in (0, 4, 1.0):
        with pytest.raises(ValueError, match="stage must be 1, 2 or 3"):
            config.reward_coefficients(stage)
    numpy_sized = FormationConfig.task("ch5-bearing", n_agents=np.int64(4), stage=np.int64(2))
    assert numpy_sized.n_agents == 4 and type(numpy_sized.n_agents) is int and type(numpy_sized.stage) is int


def test_substeps_keep_overlaps_within_the_tolerance_or_the_config_is_refused() -> None:
    """A sub-step may move an agent OVERLAP_TOLERANCE * R * min(1 - bias^dt, 0.8) / 2 (m)."""
    thesis = FormationConfig.task("ch5-bearing")  # 0.1 * 0.2 m * 0.8 / 2 = 8 mm; 0.05 m/s * 0.3 s = 15 mm: 2 sub-steps
    assert 1 - COLLISION_BIAS**0.3 > 0.8 and thesis.max_substep_travel == pytest.approx(0.008)
    assert thesis.physics_substeps == 2
    fast = FormationConfig.task("ch5-bearing", v_max=1.0)  # 0.3 m / 8 mm = 37.5: 38 sub-steps
    assert fast.physics_substeps == 38 and thesis.replace(v_max=1.0) == fast  # chosen again for the copy
    short = FormationConfig.task("ch5-bearing", dt=0.1, v_max=0.3)  # 1 - bias^0.1 = 0.469...: 0.03 m / 0.00469 m
    assert short.physics_substeps == math.ceil(0.03 / (0.1 * 0.2 * (1 - COLLISION_BIAS**0.1) / 2)) == 7
    slow = FormationConfig.task("ch5-bearing", v_max=0.01)  # 3 mm per step: the thesis's 2 sub-steps still
    assert slow.physics_substeps == 2
    given = FormationConfig.task("ch5-bearing", v_max=1.0, physics_substeps=40)
    assert given.physics_substeps == 40 and given.replace(n_agents=4).physics_substeps == 40  # given: kept
    message = r"physics_substeps=20 lets agents move 0\.0150 m per Pymunk sub-step, more than the 0\.0080 m .* >= 38"
    with pytest.raises(ValueError, match=message):
        FormationConfig.task("ch5-bearing", v_max=1.0, physics_substeps=20)
    assert pymunk.Space().collision_bias == COLLISION_BIAS  # the world's bias is Pymunk's default


def test_largest_team_that_fits_the_start_formation() -> None:
    # circumradius 0.9 * 1.2 = 1.08 m; side 2 * 1.08 * sin(pi / n): n = 16 -> 0.421 m > 0.4 m; n = 17 -> 0.397 m < 0.4 m
    assert FormationConfig.task("ch5-bearing", n_agents=16).start_side_length == pytest.approx(0.421395, abs=1e-6)
    with pytest.raises(ValueError, match=r"n_agents=17 does not fit.*at most 16"):
        FormationConfig.task("ch5-bearing", n_agents=17)


def test_a_config_that_needs_too_many_substeps_or_too_large_a_world_is_refused() -> None:
    """v_max = 1e6 m/s needs 1e6 * 0.3 / 0.008 = 37,500,000 sub-steps per step (about 100 s each): refused,
    naming v_max, dt and agent_radius; the fuzz-tested range stays allowed (v_max 1, dt 0.5, R_a 0.1: 0.5 m per step
    over 0.1 * 0.1 * 0.8 / 2 = 4 mm per sub-step = 125)."""
    with pytest.raises(ValueError, match=r"v_max=1e\+06 m/s, dt=0\.3 s and agent_radius=0\.2 m need 37,500,000 Pymunk"):
        FormationConfig.task("ch5-bearing", v_max=1e6)
    edge = FormationConfig.task("ch5-bearing", v_max=1.0, dt=0.5, agent_radius=0.1, eta_c=1.2)
    assert edge.physics_substeps == 125 <= MAX_SUBSTEPS
    with pytest.raises(ValueError, match=f"physics_substeps=5000 is invalid: it must be at most {MAX_SUBSTEPS}"):
        FormationConfig.task("ch5-bearing", physics_substeps=5000)
    for name in ("world_width", "world_height"):
        with pytest.raises(ValueError, match=f"FormationConfig.{name}=1e\\+308 is invalid: it must be at most 10000 m"):
            FormationConfig.task("ch5-bearing", **{name: 1e308})
    assert FormationConfig.task("ch5-bearing", world_width=MAX_WORLD_SIZE).world_width == 10_000.0


def test_a_config_is_written_and_read_one_way() -> None:
    """``to_dict`` is plain data (lists, chosen sub-steps as None) and ``from_dict`` gives the equal config back."""
    config = FormationConfig.task("ch4-team", n_agents=5, v_max=1.0)
    values = config.to_dict()
    assert values["stage_disabled_terms"] == [list(terms) for terms in config.stage_disabled_terms]
    assert values["physics_substeps"] is None and FormationConfig.from_dict(values) == config
    given = config.replace(physics_substeps=50)
    assert given.to_dict()["physics_substeps"] == 50 and FormationConfig.from_dict(given.to_dict()) == given
    with pytest.raises(ValueError, match=r"unknown FormationConfig field\(s\) \['colour'\]"):
        FormationConfig.from_dict({**values, "colour": "red"})
