"""Rendering: the ``rgb_array`` frame and the pygame window of ``render_mode="human"`` (headless, SDL dummy driver)."""

from __future__ import annotations

import numpy as np
import pytest

from sb3_formation import FormationConfig, FormationEnv
from sb3_formation.env.rendering import AGENT_COLOURS, GOAL, OBSTACLE, PIXELS_PER_METRE, render_frame


def test_frame_shows_obstacles_goal_agents_and_lidar() -> None:
    env = FormationEnv(FormationConfig.task("ch4-individual", stage=3))
    env.reset(seed=2)
    frame = render_frame(env.team_state(), env.config)
    height = frame.shape[0]

    def pixel(point: np.ndarray) -> tuple[int, int]:
        return int(height - point[1] * PIXELS_PER_METRE), int(point[0] * PIXELS_PER_METRE)

    for x, y, _ in env.obstacles:
        assert tuple(frame[pixel(np.array([x, y]))]) == OBSTACLE
    goal_edge = env.goal + np.array([env.config.eta_g, 0.0])
    assert tuple(frame[pixel(goal_edge - np.array([0.01, 0.0]))]) == GOAL  # on the ring
    for index, position in enumerate(env.world.positions):
        assert tuple(frame[pixel(position + 0.05)]) == AGENT_COLOURS[index]
    # the start formation (centroid at y = 2 or 8 m, radius 1.08 m) has an agent within 1.5 m of a wall
    assert (env.lidar.scan(env.world.positions)[0] < 1).any()
    assert (render_frame(env.team_state(), env.config, draw_lidar=True) != frame).any()


def test_human_mode_draws_into_a_window(monkeypatch: pytest.MonkeyPatch) -> None:
    pygame = pytest.importorskip("pygame")
    monkeypatch.setenv("SDL_VIDEODRIVER", "dummy")
    env = FormationEnv(FormationConfig.task("ch5-bearing", stage=1), render_mode="human")
    env.reset(seed=0)
    assert env.render() is None
    surface = pygame.display.get_surface()
    assert surface.get_size() == (900, 600)
    x, y = env.world.positions[0] * PIXELS_PER_METRE
    assert tuple(surface.get_at((int(x), int(600 - y))))[:3] == AGENT_COLOURS[0]
    env.close()
    assert not pygame.display.get_init()


def test_frame_shows_every_wall() -> None:
    """A corridor scene: the middle of each of its four walls is drawn in the obstacle colour, and 0.3 m beside a
    channel wall (off its 0.2 m thickness, inside the channel) is not; pixel (x, y) is row H - y ppm, column x ppm."""
    config = FormationConfig.task("ch5-bearing", scenes="corridor", stage=3)
    env = FormationEnv(config, render_mode="rgb_array")
    env.reset(seed=4)
    frame = env.render()
    height = frame.shape[0]

    def pixel(point: np.ndarray) -> np.ndarray:
        return frame[int(height - point[1] * PIXELS_PER_METRE), int(point[0] * PIXELS_PER_METRE)]

    assert len(env.walls) == 4
    for wall in env.walls:
        middle = (wall[:2] + wall[2:4]) / 2
        assert tuple(pixel(middle)) == OBSTACLE
    channel = env.walls[2]
    inside = (channel[:2] + channel[2:4]) / 2 + [0.0, 0.3 if channel[1] < env.walls[3, 1] else -0.3]
    assert tuple(pixel(inside)) != OBSTACLE
