"""The static shapes of a scene, circles and walls, and the compiled geometry every part of the engine asks of them.

A *circle* is a row (x, y, radius). A *wall* is a row (x0, y0, x1, y1, thickness): the segment from (x0, y0) to
(x1, y1) swept by a disc of diameter ``thickness``, a capsule (a rectangle with round ends), which is what Pymunk's
``Segment`` shape with a radius is. The world's border (four thick walls whose inner faces lie on [0, W] x [0, H]) is
not a wall of the scene: the kernels take the world's size for it.

One function answers each question, for the lidar, the rewards, the placement checks and the planners alike:
:func:`ray_entry` (how far along a ray a shape begins), :func:`wall_gap` and :func:`circle_gap` (how far a point is
from a shape's surface), and :func:`shape_gaps` (every point against every shape and the border, in numpy).
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

#: The columns of a wall row.
WALL_COLUMNS = ("x0", "y0", "x1", "y1", "thickness")
#: The columns of a circle row.
CIRCLE_COLUMNS = ("x", "y", "radius")


@numba.njit(cache=True)
def _convex_entry(t_enter: float, t_exit: float, start: float) -> float:  # pragma: no cover - compiled
    """The first distance >= ``start`` along a ray inside a convex part met over [t_enter, t_exit] (inf if none)."""
    if t_exit < start or t_enter > t_exit:
        return math.inf
    return max(t_enter, start)


@numba.njit(cache=True)
def circle_entry(
    px: float, py: float, ux: float, uy: float, cx: float, cy: float, radius: float, start: float
) -> float:  # pragma: no cover - compiled
    """The first distance t >= ``start`` at which the ray p + t u (u a unit vector) is inside the disc (inf if never).

    The disc is met over t = u.(c - p) -+ sqrt((u.(c - p))^2 - |c - p|^2 + r^2).
    """
    ox, oy = cx - px, cy - py
    projection = ox * ux + oy * uy
    discriminant = projection * projection - (ox * ox + oy * oy - radius * radius)
    if discriminant < 0.0:
        return math.inf
    half_chord = math.sqrt(discriminant)
    return _convex_entry(projection - half_chord, projection + half_chord, start)


@numba.njit(cache=True)
def wall_entry(px: float, py: float, ux: float, uy: float, wall: np.ndarray, start: float) -> float:  # pragma: no cover
    """The first distance t >= ``start`` at which the ray p + t u is inside the wall (inf if never).

    A wall is the union of its two end discs and the rectangle between them; the first point of a union is the first
    of its convex parts'. The rectangle is met where both slabs hold: 0 <= (p + t u - a).e <= L along the segment's
    unit e and |(p + t u - a).n| <= r across it.
    """
    ax, ay, bx, by, radius = wall[0], wall[1], wall[2], wall[3], 0.5 * wall[4]
    entry = min(circle_entry(px, py, ux, uy, ax, ay, radius, start), circle_entry(px, py, ux, uy, bx, by, radius, start))
    length = math.hypot(bx - ax, by - ay)
    if length == 0.0:
        return entry
    ex, ey = (bx - ax) / length, (by - ay) / length
    nx, ny = -ey, ex
    t_enter, t_exit = -math.inf, math.inf
    for origin, slope, low, high in (
        ((px - ax) * ex + (py - ay) * ey, ux * ex + uy * ey, 0.0, length),
        ((px - ax) * nx + (py - ay) * ny, ux * nx + uy * ny, -radius, radius),
    ):
        if slope == 0.0:
            if origin < low or origin > high:
                return entry
            continue
        first, second = (low - origin) / slope, (high - origin) / slope
        t_enter = max(t_enter, min(first, second))
        t_exit = min(t_exit, max(first, second))
    return min(entry, _convex_entry(t_enter, t_exit, start))


@numba.njit(cache=True)
def border_entry(px: float, py: float, ux: float, uy: float, width: float, height: float) -> float:  # pragma: no cover
    """The distance along the ray p + t u (p inside the world) to the border of [0, width] x [0, height]."""
    border = math.inf
    if ux > 0.0:
        border = (width - px) / ux
    elif ux < 0.0:
        border = -px / ux
    if uy > 0.0:
        border = min(border, (height - py) / uy)
    elif uy < 0.0:
        border = min(border, -py / uy)
    return border


@numba.njit(cache=True)
def wall_gap(px: float, py: float, wall: np.ndarray) -> float:  # pragma: no cover - compiled
    """Distance (m) from the point p to the wall's surface: to its segment, minus half its thickness (< 0 inside)."""
    ax, ay, bx, by = wall[0], wall[1], wall[2], wall[3]
    dx, dy = bx - ax, by - ay
    squared = dx * dx + dy * dy
    along = 0.0 if squared == 0.0 else min(max(((px - ax) * dx + (py - ay) * dy) / squared, 0.0), 1.0)
    gap: float = math.hypot(px - ax - along * dx, py - ay - along * dy) - 0.5 * wall[4]
    return gap


@numba.njit(cache=True)
def circle_gap(px: float, py: float, circle: np.ndarray) -> float:  # pragma: no cover - compiled
    """Distance (m) from the point p to the circle's surface (< 0 inside)."""
    gap: float = math.hypot(circle[0] - px, circle[1] - py) - circle[2]
    return gap


@numba.njit(cache=True)
def shape_gaps(
    points: np.ndarray, circles: np.ndarray, walls: np.ndarray, width: float, height: float
) -> np.ndarray:  # pragma: no cover - compiled
    """For every point, the distance (m) to the nearest surface of a circle, a wall or the world's border.

    :param points: ``(k, 2)`` points (m)
    :param circles: ``(m, 3)`` circles
    :param walls: ``(w, 5)`` walls
    :param width: world width (m)
    :param height: world height (m)
    :return: ``(k,)`` gaps (m), negative inside a shape
    """
    gaps = np.empty(points.shape[0])
    for index in range(points.shape[0]):
        x, y = points[index, 0], points[index, 1]
        gap = min(min(x, width - x), min(y, height - y))
        for circle in range(circles.shape[0]):
            gap = min(gap, circle_gap(x, y, circles[circle]))
        for wall in range(walls.shape[0]):
            gap = min(gap, wall_gap(x, y, walls[wall]))
        gaps[index] = gap
    return gaps


def as_walls(walls: np.ndarray | tuple[Any, ...] | list[Any]) -> np.ndarray:
    """``walls`` as a float ``(w, 5)`` array (an empty input gives ``(0, 5)``)."""
    array = np.array(walls, dtype=np.float64)
    return array.reshape(0, len(WALL_COLUMNS)) if array.size == 0 else array


def wall_lengths(walls: np.ndarray) -> np.ndarray:
    """``(w,)`` lengths (m) of the walls' segments."""
    lengths: np.ndarray = np.hypot(walls[:, 2] - walls[:, 0], walls[:, 3] - walls[:, 1])
    return lengths
