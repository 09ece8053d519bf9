"""Headless rendering of a team's state with Pillow, and an optional pygame window for ``human`` mode."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from PIL import Image, ImageDraw

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.sensors import ray_directions
from sb3_formation.env.state import TeamState

PIXELS_PER_METRE = 60
BACKGROUND = (250, 250, 247)
WALL = (60, 60, 60)
OBSTACLE = (140, 140, 150)
MOVER = (110, 80, 60)  #: moving obstacles, with a line along their last step's velocity
GOAL = (40, 170, 70)
OTHER_FORMATION = (185, 185, 185)  #: the agents of the other formations of a crossing
LINK = (90, 90, 90)
CENTROID = (200, 30, 30)
LIDAR_OBSTACLE = (255, 170, 60)
LIDAR_AGENT = (120, 160, 255)
#: matplotlib's tab10 colours: agent i is drawn in colour i mod 10
AGENT_COLOURS = [
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
    (188, 189, 34),
    (23, 190, 207),
]


def render_frame(
    state: TeamState, config: FormationConfig, draw_lidar: bool = False, pixels_per_metre: int = PIXELS_PER_METRE
) -> np.ndarray:
    """Draw a team's state: obstacles and walls, the goal ring, neighbour links, agents by index (a unicycle's heading
    as a line from its centre to its rim), the centroid.

    A pure function of the state and the config, so a recorded trajectory can be drawn without the env.

    :param state: the team's state (:meth:`FormationEnv.team_state`, or one rebuilt from a recording)
    :param config: the task configuration (world size, agent radius, goal radius, lidar range)
    :param draw_lidar: also draw every lidar ray up to its reading (obstacle channel orange, agent channel blue); needs
        a state with lidar readings
    :param pixels_per_metre: scale
    :return: ``(H, W, 3)`` uint8 image, y up
    """
    width, height = round(config.world_width * pixels_per_metre), round(config.world_height * pixels_per_metre)
    image = Image.new("RGB", (width, height), BACKGROUND)
    draw = ImageDraw.Draw(image)

    def pixel(point: np.ndarray) -> tuple[float, float]:
        return float(point[0] * pixels_per_metre), float(height - point[1] * pixels_per_metre)

    def circle(centre: np.ndarray, radius: float, **style: Any) -> None:
        x, y = pixel(centre)
        r = radius * pixels_per_metre
        draw.ellipse((x - r, y - r, x + r, y + r), **style)

    positions = state.positions
    first_mover = len(state.obstacles) - state.moving
    for index, (x, y, radius) in enumerate(state.obstacles):
        circle(np.array([x, y]), radius, fill=OBSTACLE if index < first_mover else MOVER)
    if state.obstacle_velocities is not None:  # where each mover heads: its radius along its velocity
        for (x, y, radius), velocity in zip(state.obstacles[first_mover:], state.obstacle_velocities[first_mover:]):
            speed = math.hypot(*velocity)
            if speed > 0:
                tip = np.array([x, y]) + 2 * radius * velocity / speed
                draw.line([pixel(np.array([x, y])), pixel(tip)], fill=MOVER, width=max(1, pixels_per_metre // 20))
    for x0, y0, x1, y1, thickness in state.walls:  # a capsule: a thick line with round ends
        ends = np.array([[x0, y0], [x1, y1]])
        draw.line([pixel(ends[0]), pixel(ends[1])], fill=OBSTACLE, width=max(1, round(thickness * pixels_per_metre)))
        for end in ends:
            circle(end, thickness / 2, fill=OBSTACLE)
    circle(state.goal, config.eta_g, outline=GOAL, width=max(2, pixels_per_metre // 15))
    if draw_lidar:
        if state.lidar_obstacles is None or state.lidar_agents is None:
            raise ValueError("draw_lidar needs a state with lidar readings (this one was rebuilt without them)")
        directions = ray_directions(config.lidar_rays)
        for readings, colour in ((state.lidar_obstacles, LIDAR_OBSTACLE), (state.lidar_agents, LIDAR_AGENT)):
            for position, agent_readings in zip(positions, readings):
                starts = position + config.agent_radius * directions
                ends = starts + (agent_readings * config.lidar_range)[:, None] * directions
                for start, end, reading in zip(starts, ends, agent_readings):
                    if reading < 1.0:
                        draw.line([pixel(start), pixel(end)], fill=colour, width=1)
    if state.others is not None:  # another formation's agents (a crossing): grey, outlined as agents
        for position in state.others:
            circle(position, config.agent_radius, fill=OTHER_FORMATION, outline=(0, 0, 0))
    for index, (_, succeeding) in enumerate(state.neighbours):
        draw.line([pixel(positions[index]), pixel(positions[succeeding])], fill=LINK, width=2)
    for index, position in enumerate(positions):
        circle(position, config.agent_radius, fill=AGENT_COLOURS[index % len(AGENT_COLOURS)], outline=(0, 0, 0))
    if state.headings is not None:  # a unicycle's heading: a black line from its centre to its rim
        for position, heading in zip(positions, state.headings):
            nose = position + config.agent_radius * np.array([math.cos(heading), math.sin(heading)])
            draw.line([pixel(position), pixel(nose)], fill=(0, 0, 0), width=max(2, pixels_per_metre // 20))
    cx, cy = pixel(state.centroid)
    arm = pixels_per_metre * 0.15
    draw.line([(cx - arm, cy), (cx + arm, cy)], fill=CENTROID, width=3)
    draw.line([(cx, cy - arm), (cx, cy + arm)], fill=CENTROID, width=3)
    draw.rectangle((0, 0, width - 1, height - 1), outline=WALL, width=3)
    return np.asarray(image)


class HumanWindow:
    """A pygame window showing frames (``render_mode="human"``); needs ``pip install sb3-formation[human]`` and a display.

    :param width: window width (px)
    :param height: window height (px)
    :param fps: frames per second to show at most
    """

    def __init__(self, width: int, height: int, fps: int) -> None:
        try:
            import pygame
        except ImportError as error:
            raise ImportError("render_mode='human' needs pygame: pip install 'sb3-formation[human]'") from error
        self._pygame = pygame
        pygame.init()
        pygame.display.init()
        self._screen = pygame.display.set_mode((width, height))
        pygame.display.set_caption("sb3-formation")
        self._clock = pygame.time.Clock()
        self._fps = fps

    def show(self, frame: np.ndarray) -> None:
        """Draw ``frame`` (``(H, W, 3)`` uint8) and keep the window responsive."""
        pygame = self._pygame
        pygame.event.pump()
        surface = pygame.surfarray.make_surface(np.transpose(frame, (1, 0, 2)))
        self._screen.blit(surface, (0, 0))
        pygame.display.flip()
        self._clock.tick(self._fps)

    def close(self) -> None:
        """Close the window."""
        self._pygame.display.quit()
        self._pygame.quit()
