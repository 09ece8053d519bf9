"""The slots' observation rows: each agent's own row, or, for a team critic, its row followed by its whole team's.

A slot is one agent of a stacked batch of teams (row k: agent ``k % n`` of team ``k // n``), as the SB3 ``VecEnv``,
evaluation and a trained policy's adapter see them.
"""

from __future__ import annotations

import numpy as np


def slot_observations(own: np.ndarray, n_agents: int, team_observations: bool) -> np.ndarray:
    """The slots' observations from the agents' own ``(teams * n, dim)`` observations (row k: agent ``k % n`` of team
    ``k // n``).

    :param own: the agents' own observations, whole teams one after the other
    :param n_agents: team size n
    :param team_observations: append the whole team's observations (agent 0 first) to every row, for a team critic
    :return: ``own``, or ``(teams * n, (1 + n) * dim)``
    """
    if not team_observations:
        return own
    teams = own.reshape(-1, n_agents * own.shape[-1])
    return np.hstack([own, np.repeat(teams, n_agents, axis=0)])
