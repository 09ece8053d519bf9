"""Formations that cross: the crossing scenes, formations sharing one world, and their episodes."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pymunk
import pytest

from sb3_formation.env.auto_reset import EngineBlock
from sb3_formation.env.config import FormationConfig
from sb3_formation.env.engine import ContactColumn, FormationEngine
from sb3_formation.env.families import CROSSING_JITTER
from sb3_formation.env.scenarios import Scenario, start_formation
from sb3_formation.env.scenes import scenes_named
from sb3_formation.env.sensors import AGENT_CHANNEL, OBSTACLE_CHANNEL

CONFIG = FormationConfig(scenes="crossing")  # n = 6, 15 m x 10 m, R_a = 0.2 m, lidar range 1.5 m
N = CONFIG.n_agents


def formation(centroid: tuple[float, float], goal: tuple[float, float]) -> Scenario:
    return Scenario(start_formation(CONFIG, np.array(centroid)), np.array(goal))


def crossing_engine(*parts: Scenario, teams: int = 2) -> FormationEngine:
    engine = FormationEngine([CONFIG] * teams)
    engine.reset(0, scenario=parts)
    return engine


@pytest.mark.parametrize("scenes", ["crossing", "crossing-4"])
def test_the_ways_of_a_crossing_cross_near_the_centre(scenes: str) -> None:
    """Twenty draws: every formation fits the world, starts clear of the others, and flies a diameter through one
    centre within the documented jitter of the world's; two formations cross at 60-120 degrees, four fly two
    head-on pairs about 90 degrees apart (each direction within 10 degrees of its place). The same seed draws the
    same crossing."""
    config, family = CONFIG.replace(scenes=scenes), scenes_named(scenes)
    rng = np.random.default_rng(5)
    for _ in range(20):
        parts = family.draw_formations(config, 3, rng)
        assert len(parts) == family.formations
        for part in parts:
            part.validate(config)
        centres = np.array([(part.centroid + part.goal) / 2 for part in parts])
        np.testing.assert_allclose(centres, np.repeat(centres[:1], len(parts), axis=0), atol=1e-9)
        assert np.all(np.abs(centres[0] - [7.5, 5.0]) <= CROSSING_JITTER + 1e-12)
        starts = np.array([part.centroid for part in parts])
        gaps = [np.hypot(*(starts[i] - starts[j])) for i in range(len(parts)) for j in range(i)]
        assert min(gaps) >= 2 * (1.28 + 0.3) - 1e-9  # two starting footprints and the placement room
        directions = [math.atan2(*(part.goal - part.centroid)[::-1]) for part in parts]
        turns = [math.degrees((angle - directions[0]) % (2 * math.pi)) for angle in directions]
        if family.formations == 2:
            assert 60 - 1e-9 <= min(turns[1], 360 - turns[1]) <= 120 + 1e-9
        else:
            for place, turn in enumerate(turns):
                assert abs((turn - 90 * place + 180) % 360 - 180) <= 20 + 1e-9
    first, second = (family.draw_formations(config, 3, np.random.default_rng(9)) for _ in range(2))
    for one, other in zip(first, second, strict=True):
        np.testing.assert_array_equal(one.agent_positions, other.agent_positions)
        np.testing.assert_array_equal(one.goal, other.goal)
    with pytest.raises(ValueError, match=rf"could not draw a '{scenes}' scene in the 5 m x 4 m world for"):
        FormationEngine([config.replace(world_width=5.0, world_height=4.0)] * 4)


def test_the_lidar_sees_the_other_formation_on_the_agent_channel_where_a_ray_cast_puts_it() -> None:
    """Two formations face each other 3 m apart: after every step each agent's agent-channel readings equal Pymunk's
    own ray cast against the agents it sees (its team's but itself and its ring neighbours, and every agent of the
    other formation, at their world positions); the other formation's agents never appear on the obstacle channel."""
    engine = crossing_engine(formation((5.0, 5.0), (12.0, 5.0)), formation((8.0, 5.0), (1.0, 5.0)))
    world = engine.worlds[0]
    assert world is not None and world is engine.worlds[1]
    seen = 0
    for step in range(6):
        engine.step(np.zeros((2 * N, 2)))
        everyone = world.agent_states[:, :2]
        np.testing.assert_array_equal(everyone, engine.latest.positions)
        for team in (0, 1):
            rows = engine.team_rows(team)
            readings = engine.episodes.lidar[AGENT_CHANNEL, rows]
            assert np.all(engine.episodes.lidar[OBSTACLE_CHANNEL, rows] > 0.99)  # the border only, far away
            for agent in range(N):
                space, others = pymunk.Space(), set()
                own = rows.start + agent
                neighbours = rows.start + engine.constants.neighbours[own]
                for other in range(2 * N):
                    if other != own and other not in neighbours:
                        circle = pymunk.Circle(space.static_body, CONFIG.agent_radius, tuple(everyone[other]))
                        space.add(circle)
                        if not rows.start <= other < rows.stop:
                            others.add(circle)
                for ray, direction in enumerate(engine.lidars[team].directions):
                    start = everyone[own] + CONFIG.agent_radius * direction
                    end = start + CONFIG.lidar_range * direction
                    hit = space.segment_query_first(tuple(start), tuple(end), 0.0, pymunk.ShapeFilter())
                    expected = 1.0 if hit is None else hit.alpha
                    seen += hit is not None and hit.shape in others
                    assert readings[agent, ray] == pytest.approx(expected, abs=1e-9), (step, team, agent, ray)
    assert seen > 0


def test_formations_driven_into_each_other_touch_as_agents() -> None:
    """Two formations driven head-on at full force: their front agents touch, and every touch between them is an
    agent contact of both (pushed, never overlapping by more than Pymunk's slop), never an obstacle contact."""
    engine = crossing_engine(formation((5.0, 5.0), (12.0, 5.0)), formation((8.0, 5.0), (1.0, 5.0)))
    actions = np.repeat([[1.0, 0.0], [-1.0, 0.0]], N, axis=0)
    touched = np.zeros(2 * N, dtype=np.int64)
    for _ in range(80):
        step = engine.step(actions)
        touched += step.contacts[:, ContactColumn.AGENTS]
        assert not step.contacts[:, ContactColumn.OBSTACLES].any()
        apart = np.hypot(*(step.positions[:N, None] - step.positions[None, N:]).transpose(2, 0, 1))
        assert apart.min() >= 2 * CONFIG.agent_radius - 0.01
    assert touched[:N].sum() > 0 and touched[N:].sum() > 0
    assert engine.episode_summary(0)["collisions_agent"] > 0


def test_formations_out_of_each_other_s_reach_fly_as_if_alone() -> None:
    """Two formations 6 m apart (beyond every lidar reading of each other) under the same random actions: each plays
    exactly the episode it plays alone in a world of its own: positions, observations and rewards, bit for bit."""
    low, high = formation((3.0, 2.0), (12.0, 2.0)), formation((12.0, 8.0), (3.0, 8.0))
    together = crossing_engine(low, high)
    alone = [FormationEngine([CONFIG.replace(scenes="passage")]) for _ in range(2)]
    for engine, part in zip(alone, (low, high)):
        engine.reset(0, scenario=part)
    rng = np.random.default_rng(3)
    for _ in range(60):
        actions = rng.uniform(-1.0, 1.0, (2 * N, 2))
        step = together.step(actions)
        for team, engine in enumerate(alone):
            rows = together.team_rows(team)
            own = engine.step(actions[rows])
            np.testing.assert_array_equal(step.positions[rows], own.positions)
            np.testing.assert_array_equal(step.observations[rows], own.observations)
            np.testing.assert_array_equal(step.rewards[rows], own.rewards)


def test_a_formation_that_ended_stands_as_an_obstacle_until_the_crossing_restarts() -> None:
    """A formation that starts at its goal ends in the first step: its agents are halted (its actions no longer move
    them), the other formation's lidar sees them on the obstacle channel and flies on; resetting the crossing lets
    both fly again."""
    engine = crossing_engine(formation((4.0, 5.0), (4.0, 5.0)), formation((8.0, 5.0), (12.0, 5.0)))
    step = engine.step(np.zeros((2 * N, 2)))
    assert step.terminated.tolist() == [True, False] and engine.live.tolist() == [False, True]
    world = engine.worlds[0]
    assert world is not None and world.halted.tolist() == [True] * N + [False] * N
    layout = engine.lidars[1].layout
    assert layout.channels[-2 * N : -N].tolist() == [OBSTACLE_CHANNEL] * N  # the other formation's agents
    before = world.agent_states[:N, :2].copy()
    for _ in range(5):
        engine.step(np.ones((2 * N, 2)))
    np.testing.assert_array_equal(world.agent_states[:N, :2], before)
    assert engine.latest.positions[N:, 0].min() > 8.0 - 1.28  # the other flew on (towards +x)
    engine.reset(0, seed=1)
    assert engine.live.tolist() == [True, True] and not world.halted.any()
    assert engine.lidars[1].layout.channels[-2 * N : -N].tolist() == [AGENT_CHANNEL] * N


def test_a_crossing_is_refused_where_it_cannot_fly() -> None:
    """A crossing needs its formations together: an engine of one team, the reset of a team that is not its unit's
    first, a placement of the wrong number of formations, and automatic resets (training) are refused in one line."""
    with pytest.raises(ValueError, match=r"^the 'crossing' scenes fly 2 formations together: give a multiple of 2"):
        FormationEngine([CONFIG])
    engine = crossing_engine(formation((5.0, 5.0), (12.0, 5.0)), formation((8.0, 2.0), (8.0, 8.0)))
    with pytest.raises(ValueError, match=r"^team 1 flies in the crossing of team 0: reset that team$"):
        engine.reset(1)
    with pytest.raises(TypeError, match=r"^the scenario must be 2 Scenarios, one per formation, got tuple$"):
        engine.reset(0, scenario=(formation((5.0, 5.0), (12.0, 5.0)),))
    with pytest.raises(ValueError, match=r"^the 'crossing' scenes fly formations together and are played, not trained"):
        EngineBlock([CONFIG] * 2, auto_reset=True)


def test_the_episode_loop_starts_a_crossing_s_formations_together() -> None:
    """Five episodes of two formations with the shrinking controller, 50 steps each: rounded up to three whole
    crossings, formations 2k and 2k + 1 drawn from seed + 2k; two worker processes play the same rows."""
    from sb3_formation.experiment.evaluation import evaluate
    from sb3_formation.experiment.targets import load_policy

    policy = load_policy("controller:shrinking")
    overrides = {"scenes": "crossing", "max_steps": 50}
    one = evaluate(policy, 5, seed=7, n_envs=2, env_overrides=overrides, record=0)
    assert [row["episode"] for row in one.episodes] == [0, 1, 2, 3, 4, 5]
    assert [row["seed"] for row in one.episodes] == [7, 7, 9, 9, 11, 11]
    assert [row["length"] for row in one.episodes] == [50] * 6
    two = evaluate(policy, 6, seed=7, n_envs=4, env_overrides=overrides, n_workers=2, record=0)
    three = evaluate(policy, 6, seed=7, n_envs=4, env_overrides=overrides, n_workers=1, record=0)
    assert two.episodes == three.episodes
    for row, other in zip(one.episodes, two.episodes, strict=True):
        assert row["final_goal_distance"] == other["final_goal_distance"]  # the same crossings, fewer at once


def test_training_on_crossings_is_refused_before_writing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``sb3-formation train`` on the crossing scenes stops with one line and leaves no run folder."""
    from sb3_formation.cli import main

    run = tmp_path / "run"
    arguments = ["train", "--recipe", "ch5-bearing", "--env", "scenes=crossing", "--run-dir", str(run), "--no-progress"]
    assert main(arguments) == 2
    assert capsys.readouterr().err.strip().endswith("played, not trained on: evaluate or benchmark a policy on them")
    assert not run.exists()


def test_the_filter_keeps_formations_driven_into_each_other_apart() -> None:
    """The head-on formations of :func:`test_formations_driven_into_each_other_touch_as_agents`, each agent's full-force
    action through the safety filter (its own row only): the other formation's agents are on the agent channel, so
    each agent takes its half of the barrier, and no two agents touch on a step the filter reports feasible (none is
    infeasible here: the formations stop face to face)."""
    from sb3_formation.safety.filter import SafetyFilter

    engine = crossing_engine(formation((5.0, 5.0), (12.0, 5.0)), formation((8.0, 5.0), (1.0, 5.0)))
    safety = SafetyFilter(CONFIG)
    actions = np.repeat([[1.0, 0.0], [-1.0, 0.0]], N, axis=0)
    changed = 0
    for _ in range(80):
        safe, report = safety.filter(engine.latest.observations, actions)
        changed += int((safe != actions).any(axis=1).sum())
        step = engine.step(safe)
        if step.contacts[:, ContactColumn.AGENTS].any():
            assert report.infeasible.any()
        apart = np.hypot(*(step.positions[:N, None] - step.positions[None, N:]).transpose(2, 0, 1))
        if not report.infeasible.any():
            assert apart.min() >= 2 * CONFIG.agent_radius
    assert changed > 0
    assert engine.episode_summary(0)["collisions_agent"] == engine.episode_summary(1)["collisions_agent"] == 0


def test_an_agent_that_fails_in_a_crossing_stops_in_the_shared_world() -> None:
    """Failures at step 0 in a crossing: each formation flies the ring of 5; the failed agents are the halted bodies of
    the shared world at their formation's places, and each formation sees the other's failed agent on the obstacle
    channel, its flying agents on the agent channel."""
    from sb3_formation.env.disturbances import Disturbances, Failures

    config = CONFIG.replace(disturbances=Disturbances(failures=Failures(probability=1.0, steps=(0, 0))))
    engine = FormationEngine([config] * 2)
    engine.reset(0, seed=4, scenario=(formation((5.0, 5.0), (12.0, 5.0)), formation((9.0, 5.0), (1.0, 5.0))))
    failed = [int(np.flatnonzero(~engine.constants.flying[engine.team_rows(team)])[0]) for team in (0, 1)]
    world = engine.worlds[0]
    assert world is not None
    assert np.flatnonzero(world.halted).tolist() == [failed[0], N + failed[1]]
    for team, other in ((0, 1), (1, 0)):
        channels = engine.lidars[team].layout.channels[-2 * N : -N]
        expected = [OBSTACLE_CHANNEL if agent == failed[other] else AGENT_CHANNEL for agent in range(N)]
        assert channels.tolist() == expected
    start = world.agent_states[[failed[0], N + failed[1]], :2].copy()
    for _ in range(3):
        engine.step(np.ones((2 * N, 2)))
    np.testing.assert_array_equal(world.agent_states[[failed[0], N + failed[1]], :2], start)
