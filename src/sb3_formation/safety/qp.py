"""The safety filter's quadratic program, one per agent, and its two solvers: a compiled exact one and a library's.

Each agent's problem has three variables ``x = (u_x, u_y, s)``: the commanded velocity u of the point it controls (in
units of v_max) and one slack s (in units of a step's travel v_max dt) shared by its safety constraints::

    minimise    |u - t|^2 + rho s^2
    subject to  g_k . u - s <= h_k      (safety: barriers, :mod:`sb3_formation.safety.filter`)
                a_j . u     <= b_j      (hard: action bounds and the speed limit)
                -s          <= 0

with t the velocity the proposed action commands. A row of the constraint matrix is ``(g_x, g_y, -1)`` for a safety
constraint and ``(a_x, a_y, 0)`` for a hard one. The objective is strictly convex, so the solution is unique.

:func:`solve_rows` is the compiled solver: if t with s = 0 keeps every constraint it is the solution (returned
unchanged, bit for bit); otherwise it searches the active sets of at most three constraints, smallest first, each
containing a constraint that t violates (the optimum's active set always does: if t kept all of its active
constraints, t itself would minimise the problem restricted to them), and returns the first point that keeps every
constraint with non-negative multipliers: the Karush-Kuhn-Tucker point, hence the optimum. :func:`solve_with_library`
solves the same problem with a solver of ``qpsolvers``; the tests hold the two within 1e-6 of each other on fuzzed
problems.
"""

from __future__ import annotations

import numba
import numpy as np

#: Tolerance on a constraint's residual (in units of the variables) and on a multiplier's sign.
FEASIBILITY_TOLERANCE = 1e-9


@numba.njit(cache=True)
def _keeps_all(x0: float, x1: float, x2: float, rows: np.ndarray, rhs: np.ndarray, count: int) -> bool:  # pragma: no cover
    for k in range(count):
        if rows[k, 0] * x0 + rows[k, 1] * x1 + rows[k, 2] * x2 > rhs[k] + FEASIBILITY_TOLERANCE:
            return False
    return True


@numba.njit(cache=True)
def _solve_small(matrix: np.ndarray, vector: np.ndarray, size: int) -> tuple[bool, np.ndarray]:  # pragma: no cover
    """``matrix[:size, :size] y = vector[:size]`` by Gaussian elimination with partial pivoting; False if singular."""
    a = matrix[:size, :size].copy()
    b = vector[:size].copy()
    scale = 0.0
    for i in range(size):
        for j in range(size):
            scale = max(scale, abs(a[i, j]))
    if scale == 0.0:
        return False, b
    for column in range(size):
        pivot = column
        for row in range(column + 1, size):
            if abs(a[row, column]) > abs(a[pivot, column]):
                pivot = row
        if abs(a[pivot, column]) <= 1e-12 * scale:
            return False, b
        if pivot != column:
            for j in range(size):
                a[column, j], a[pivot, j] = a[pivot, j], a[column, j]
            b[column], b[pivot] = b[pivot], b[column]
        for row in range(column + 1, size):
            factor = a[row, column] / a[column, column]
            for j in range(column, size):
                a[row, j] -= factor * a[column, j]
            b[row] -= factor * b[column]
    for row in range(size - 1, -1, -1):
        total = b[row]
        for j in range(row + 1, size):
            total -= a[row, j] * b[j]
        b[row] = total / a[row, row]
    return True, b


@numba.njit(cache=True)
def _try_active_set(
    active: np.ndarray, size: int, target: np.ndarray, weights: np.ndarray, rows: np.ndarray, rhs: np.ndarray, count: int
) -> tuple[bool, np.ndarray]:  # pragma: no cover - compiled
    """The minimiser of the objective with the constraints ``active[:size]`` held as equalities, if it keeps every
    constraint with multipliers >= 0 (then it is the optimum)."""
    # x = x0 - W^-1 G_A^T lam / 2 with W = diag(weights); G_A x = h_A  =>  (G_A W^-1 G_A^T / 2) lam = G_A x0 - h_A
    matrix = np.zeros((3, 3))
    vector = np.zeros(3)
    for i in range(size):
        a = active[i]
        vector[i] = rows[a, 0] * target[0] + rows[a, 1] * target[1] + rows[a, 2] * target[2] - rhs[a]
        for j in range(size):
            b = active[j]
            total = 0.0
            for d in range(3):
                total += rows[a, d] * rows[b, d] / weights[d]
            matrix[i, j] = 0.5 * total
    solved, multipliers = _solve_small(matrix, vector, size)
    x = target.copy()
    if not solved:
        return False, x
    for i in range(size):
        if multipliers[i] < -FEASIBILITY_TOLERANCE:
            return False, x
        for d in range(3):
            x[d] -= 0.5 * multipliers[i] * rows[active[i], d] / weights[d]
    return _keeps_all(x[0], x[1], x[2], rows, rhs, count), x


@numba.njit(cache=True)
def solve_one(
    target: np.ndarray, slack_weight: float, rows: np.ndarray, rhs: np.ndarray, count: int
) -> np.ndarray:  # pragma: no cover
    """The optimum ``(u_x, u_y, s)`` of one agent's problem (see the module docstring).

    :param target: ``(2,)`` the proposed commanded velocity t
    :param slack_weight: rho
    :param rows: ``(m, 3)`` constraint rows (the first ``count`` are used)
    :param rhs: ``(m,)`` right-hand sides
    :param count: number of constraints
    """
    x0 = np.array([target[0], target[1], 0.0])
    if _keeps_all(x0[0], x0[1], x0[2], rows, rhs, count):
        return x0
    weights = np.array([1.0, 1.0, slack_weight])
    violated = np.zeros(count, dtype=np.bool_)
    for k in range(count):
        violated[k] = rows[k, 0] * x0[0] + rows[k, 1] * x0[1] + rows[k, 2] * x0[2] > rhs[k] + FEASIBILITY_TOLERANCE
    active = np.zeros(3, dtype=np.int64)
    for i in range(count):  # one active constraint
        if violated[i]:
            active[0] = i
            found, x = _try_active_set(active, 1, x0, weights, rows, rhs, count)
            if found:
                return x
    for i in range(count):  # two, one of them violated (each pair once)
        for j in range(i + 1, count):
            if violated[i] or violated[j]:
                active[0], active[1] = i, j
                found, x = _try_active_set(active, 2, x0, weights, rows, rhs, count)
                if found:
                    return x
    for i in range(count):  # three
        for j in range(i + 1, count):
            for k in range(j + 1, count):
                if violated[i] or violated[j] or violated[k]:
                    active[0], active[1], active[2] = i, j, k
                    found, x = _try_active_set(active, 3, x0, weights, rows, rhs, count)
                    if found:
                        return x
    # unreachable for a feasible problem (the slack makes every problem whose hard constraints meet feasible); keep the
    # target rather than return garbage, and let the caller see the slack it needed as infinite
    return np.array([target[0], target[1], np.inf])


@numba.njit(cache=True)
def solve_rows(
    targets: np.ndarray, slack_weight: float, rows: np.ndarray, rhs: np.ndarray, counts: np.ndarray
) -> np.ndarray:  # pragma: no cover - compiled
    """:func:`solve_one` for every agent: ``(k, 3)`` solutions for ``(k, 2)`` targets, ``(k, m, 3)`` rows, ``(k, m)``
    right-hand sides and ``(k,)`` constraint counts."""
    solutions = np.empty((targets.shape[0], 3))
    for agent in range(targets.shape[0]):
        solutions[agent] = solve_one(targets[agent], slack_weight, rows[agent], rhs[agent], counts[agent])
    return solutions


def solve_with_library(target: np.ndarray, slack_weight: float, rows: np.ndarray, rhs: np.ndarray, solver: str) -> np.ndarray:
    """The same problem as :func:`solve_one`, solved by ``qpsolvers`` with ``solver`` (``"daqp"``, ``"quadprog"``, ...).

    :raises ValueError: the solver found no solution
    """
    import qpsolvers  # only this path needs it

    weights = np.array([1.0, 1.0, slack_weight])
    solution = qpsolvers.solve_qp(
        np.diag(2.0 * weights), np.r_[-2.0 * np.asarray(target, dtype=np.float64), 0.0], rows, rhs, solver=solver
    )
    if solution is None:
        raise ValueError(f"the QP solver {solver!r} found no solution of a safety filter problem")
    return np.asarray(solution, dtype=np.float64)


def check_solver(solver: str) -> None:
    """Refuse a ``qpsolvers`` solver that is not installed here (``qpsolvers.available_solvers``); ``"fast"``, the
    compiled solver, always is. Recipes and model files are checked with it before anything is written.

    :raises ValueError: naming the solver, the ones available and how to install it
    """
    if solver == "fast":
        return
    try:
        import qpsolvers
    except ImportError:
        available: list[str] = []
    else:
        available = list(qpsolvers.available_solvers)
    if solver not in available:
        raise ValueError(
            f"the QP solver {solver!r} is not installed here (available: {', '.join(['fast', *available])}): "
            f"pip install 'qpsolvers[{solver}]', or use solver: fast"
        )
