"""Clearance maps: how far each point of a grid over the world is from the nearest shape, and paths through them.

The scene families use a map to refuse scenes that no team can solve (:func:`reachable`); the privileged planner
plans its centroid path on one (:func:`shortest_path`); the goal term of ``goal_progress: geodesic`` measures the way
round the shapes on one (:func:`goal_field`, :func:`path_distance`). A team's *footprint* is the disc around its centroid that
holds all its agents: a formation of circumradius r has footprint radius r + R_a, and the smallest a team can take
(:func:`shrunk_footprint`) is the n-gon whose neighbours touch, of circumradius R_a / sin(pi / n).
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass
from typing import cast

import numba
import numpy as np

from sb3_formation.env.config import FormationConfig
from sb3_formation.env.shapes import shape_gaps

#: Grid spacing (m) of clearance maps: a quarter of the thesis's 0.4 m agent diameter.
GRID_SPACING = 0.1


def start_footprint(config: FormationConfig) -> float:
    """Footprint radius (m) of the starting formation: its circumradius plus R_a (1.28 m for the thesis's n = 6)."""
    return config.start_circumradius + config.agent_radius


def shrunk_footprint(config: FormationConfig) -> float:
    """Footprint radius (m) of the smallest formation: neighbours touching (side 2 R_a), circumradius
    R_a / sin(pi / n), plus R_a (0.6 m for n = 6)."""
    return config.agent_radius / math.sin(math.pi / config.n_agents) + config.agent_radius


@dataclass(frozen=True)
class ClearanceMap:
    """The gap (m) from the centres of a grid's cells to the nearest circle, wall or border of a scene.

    :param gaps: ``(rows, columns)`` gaps; row j, column i is the point ((i + 0.5) h, (j + 0.5) h)
    :param spacing: grid spacing h (m)
    """

    gaps: np.ndarray
    spacing: float

    @classmethod
    def of(
        cls, config: FormationConfig, circles: np.ndarray, walls: np.ndarray, spacing: float = GRID_SPACING
    ) -> ClearanceMap:
        """The map of a scene's shapes in ``config``'s world."""
        columns, rows = math.ceil(config.world_width / spacing), math.ceil(config.world_height / spacing)
        xs, ys = (np.arange(columns) + 0.5) * spacing, (np.arange(rows) + 0.5) * spacing
        points = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
        gaps = shape_gaps(points, np.asarray(circles, float).reshape(-1, 3), walls, config.world_width, config.world_height)
        return cls(gaps.reshape(rows, columns), spacing)

    def cell(self, point: np.ndarray) -> tuple[int, int]:
        """The (row, column) of the cell holding ``point`` (m), clipped to the grid."""
        rows, columns = self.gaps.shape
        column = min(max(int(point[0] / self.spacing), 0), columns - 1)
        row = min(max(int(point[1] / self.spacing), 0), rows - 1)
        return row, column

    def point(self, cell: tuple[int, int]) -> np.ndarray:
        """The centre (m) of a cell."""
        return (np.array([cell[1], cell[0]], dtype=float) + 0.5) * self.spacing

    def goal_cells(self, goal: np.ndarray, radius: float) -> np.ndarray:
        """``(rows, columns)`` bool: the cells whose centre lies within ``radius`` (m) of ``goal``."""
        rows, columns = self.gaps.shape
        ys, xs = (np.arange(rows) + 0.5) * self.spacing, (np.arange(columns) + 0.5) * self.spacing
        cells: np.ndarray = np.hypot(xs[None, :] - goal[0], ys[:, None] - goal[1]) <= radius
        return cells


def reachable(clearance: ClearanceMap, start: np.ndarray, goal: np.ndarray, goal_radius: float, footprint: float) -> bool:
    """Whether a disc of radius ``footprint`` (m) can move from ``start`` to within ``goal_radius`` of ``goal``
    through cells whose gap is at least the footprint (8-connected cells).

    :param clearance: the scene's map
    :param start: ``(2,)`` the disc's start (m)
    :param goal: ``(2,)`` the goal (m)
    :param goal_radius: how close (m) the disc's centre must come to the goal
    :param footprint: the disc's radius (m)
    """
    return shortest_path(clearance, start, goal, goal_radius, footprint) is not None


def shortest_path(
    clearance: ClearanceMap,
    start: np.ndarray,
    goal: np.ndarray,
    goal_radius: float,
    footprint: float,
    gap_weight: float = 0.0,
) -> np.ndarray | None:
    """The cheapest 8-connected path of cell centres along which a disc of radius ``footprint`` fits, from the cell
    of ``start`` to a cell within ``goal_radius`` of ``goal`` (Dijkstra, A*'s heuristic being 0), or ``None``.

    A move between neighbouring cells costs its length times ``1 + gap_weight / (gap - footprint + h)`` at the cell
    entered (h the spacing), so a positive weight keeps the path away from shapes where there is room.

    :return: ``(k, 2)`` points (m), ``start`` first, or ``None`` when the goal cannot be reached
    """
    free = clearance.gaps >= footprint
    targets = clearance.goal_cells(goal, goal_radius) & free
    first = clearance.cell(start)
    if not free[first] or not targets.any():
        return None
    penalty = 1.0 + gap_weight / (np.maximum(clearance.gaps - footprint, 0.0) + clearance.spacing)
    end_row, end_column, came_from = _dijkstra(free, targets, penalty, first[0], first[1])
    if end_row < 0:
        return None
    cells = [(end_row, end_column)]
    while cells[-1] != first:
        cells.append(cast("tuple[int, int]", tuple(int(value) for value in came_from[cells[-1]])))  # a (row, column)
    path = np.array([clearance.point(cell) for cell in reversed(cells)])
    path[0] = start
    return path


@numba.njit(cache=True)
def _dijkstra(
    free: np.ndarray, targets: np.ndarray, penalty: np.ndarray, row: int, column: int
) -> tuple[int, int, np.ndarray]:  # pragma: no cover - compiled
    """Dijkstra over the free cells from (row, column) to the nearest target: (the target's row and column, or -1,
    and each cell's predecessor)."""
    rows, columns = free.shape
    cost = np.full(free.shape, np.inf)
    came_from = np.full((rows, columns, 2), -1, dtype=np.int64)
    cost[row, column] = 0.0
    queue = [(0.0, row, column)]
    while len(queue) > 0:
        current, r, c = heapq.heappop(queue)
        if current > cost[r, c]:
            continue
        if targets[r, c]:
            return r, c, came_from
        for dr in range(-1, 2):
            for dc in range(-1, 2):
                nr, nc = r + dr, c + dc
                if (dr == 0 and dc == 0) or nr < 0 or nr >= rows or nc < 0 or nc >= columns or not free[nr, nc]:
                    continue
                candidate = current + math.sqrt(dr * dr + dc * dc) * penalty[nr, nc]
                if candidate < cost[nr, nc]:
                    cost[nr, nc] = candidate
                    came_from[nr, nc, 0], came_from[nr, nc, 1] = r, c
                    heapq.heappush(queue, (candidate, nr, nc))
    return -1, -1, came_from


#: Reach (m) of :func:`path_distance`: the cells it goes straight to from a point lie within this distance.
PATH_REACH = 0.5


def goal_field(clearance: ClearanceMap, goal: np.ndarray) -> np.ndarray:
    """The length (m) of the shortest 16-connected way from each cell's centre to ``goal`` through cells whose centre
    lies outside every shape (Dijkstra from the goal's cell); ``inf`` where there is none (inside a shape).

    :param clearance: the scene's map
    :param goal: ``(2,)`` the goal (m)
    """
    row, column = clearance.cell(goal)
    start = float(np.hypot(*(clearance.point((row, column)) - goal))) / clearance.spacing
    return _distances_from(clearance.gaps > 0.0, row, column, start) * clearance.spacing


def path_distance(clearance: ClearanceMap, field: np.ndarray, point: np.ndarray) -> float:
    """The way (m) from ``point`` to the goal of ``field`` (:func:`goal_field` of ``clearance``): the least, over the
    cells the point sees, of the straight distance to a cell's centre plus the cell's way. The point sees the cells
    within :data:`PATH_REACH` of it and inside the free disc around it (closer than its cell's gap less a cell's
    diagonal), so no straight part crosses a shape; this far from the grid's cells, a small move changes the way by
    nearly the move's share towards the goal.

    :param clearance: the scene's map
    :param field: its :func:`goal_field`
    :param point: ``(2,)`` the point (m), e.g. a team's centroid
    :return: the way (m); where the point sees no cell with a way (it lies in a shape, as the centroid of a ring of
        agents round a circle can), the least over every cell of the straight distance plus the cell's way
    """
    spacing = clearance.spacing
    row, column = clearance.cell(point)
    reach = min(PATH_REACH, float(clearance.gaps[row, column]) - math.sqrt(2) * spacing)
    cells = max(int(reach / spacing), 1)
    low_row, low_column = max(row - cells, 0), max(column - cells, 0)
    block = field[low_row : row + cells + 1, low_column : column + cells + 1]
    ys = (np.arange(low_row, low_row + block.shape[0]) + 0.5) * spacing
    xs = (np.arange(low_column, low_column + block.shape[1]) + 0.5) * spacing
    straight = np.hypot(xs[None, :] - point[0], ys[:, None] - point[1])
    seen = straight <= max(reach, 1.5 * spacing)
    way = float(np.where(seen, block + straight, np.inf).min())
    if math.isinf(way):  # inside a shape (a ring of agents round a circle): the straight way to any cell
        rows_y, columns_x = (np.arange(field.shape[0]) + 0.5) * spacing, (np.arange(field.shape[1]) + 0.5) * spacing
        way = float((field + np.hypot(columns_x[None, :] - point[0], rows_y[:, None] - point[1])).min())
    return way


#: The moves of :func:`_distances_from`: to the 8 neighbours and the 8 knight's-move cells (16-connected: in the
#: open a way shortens within 5 % of the straight distance covered, against 8 % with 8 neighbours).
MOVES = np.array([(dr, dc) for dr in range(-2, 3) for dc in range(-2, 3) if max(abs(dr), abs(dc)) == 1 or abs(dr * dc) == 2])


@numba.njit(cache=True)
def _distances_from(free: np.ndarray, row: int, column: int, start: float) -> np.ndarray:  # pragma: no cover - compiled
    """Dijkstra over the free cells from (row, column), whose cost is ``start`` (in cells): every free cell's cost.
    A knight's move also needs the two cells it passes between free."""
    rows, columns = free.shape
    cost = np.full(free.shape, np.inf)
    cost[row, column] = start
    queue = [(start, row, column)]
    while len(queue) > 0:
        current, r, c = heapq.heappop(queue)
        if current > cost[r, c]:
            continue
        for move in range(MOVES.shape[0]):
            dr, dc = MOVES[move, 0], MOVES[move, 1]
            nr, nc = r + dr, c + dc
            if nr < 0 or nr >= rows or nc < 0 or nc >= columns or not free[nr, nc]:
                continue
            if abs(dc) == 2 and not (free[r, c + dc // 2] and free[nr, c + dc // 2]):
                continue
            if abs(dr) == 2 and not (free[r + dr // 2, c] and free[r + dr // 2, nc]):
                continue
            candidate = current + math.sqrt(dr * dr + dc * dc)
            if candidate < cost[nr, nc]:
                cost[nr, nc] = candidate
                heapq.heappush(queue, (candidate, nr, nc))
    return cost
