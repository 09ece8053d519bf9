"""The recurrent rollout buffer: SB3's ``RolloutBuffer`` plus each step's hidden states and messages, served as padded,
masked minibatches of whole sequences (cut at episode starts and every ``max_sequence_length`` steps; with messages,
whole teams' sequences)."""

from __future__ import annotations

from collections.abc import Generator, Sequence
from typing import NamedTuple

import numpy as np
import torch as th
from stable_baselines3.common.buffers import RolloutBuffer

from sb3_formation.env.geometry import ring_rows
from sb3_formation.sb3.recurrent.policies import RecurrentStates


class SequenceBatch(NamedTuple):
    """A minibatch of whole sequences, ``(L, B, ...)``, padded after each sequence's end (``mask`` False there)."""

    observations: th.Tensor
    actions: th.Tensor
    old_values: th.Tensor
    old_log_prob: th.Tensor
    advantages: th.Tensor
    returns: th.Tensor
    mask: th.Tensor
    states: RecurrentStates
    neighbours: th.Tensor | None  #: ``(B, 2)`` each column's ring neighbours' columns (with messages), else ``None``


class SequenceLayout(NamedTuple):
    """How a rollout of ``T`` steps and ``N`` slots splits into sequences (slot-major: slot 0's sequences first).

    :ivar sequence: ``(N * T,)`` sequence of each step, steps in slot-major order (index ``slot * T + t``)
    :ivar position: ``(N * T,)`` position of each step within its sequence
    :ivar lengths: ``(S,)`` sequence lengths
    :ivar slots: ``(S,)`` slot of each sequence
    :ivar first_steps: ``(S,)`` time step at which each sequence starts
    """

    sequence: np.ndarray
    position: np.ndarray
    lengths: np.ndarray
    slots: np.ndarray
    first_steps: np.ndarray


def sequence_layout(episode_starts: np.ndarray, max_length: int | None = None) -> SequenceLayout:
    """Cut each slot's steps into sequences at the rollout's start, at every episode start and, with ``max_length``,
    every ``max_length`` steps of the rollout (t = 0, max_length, 2 max_length, ...).

    :param episode_starts: ``(T, N)`` flags: the step is the first of an episode
    :param max_length: longest sequence (``None``: the rollout's length)
    """
    steps = episode_starts.shape[0]
    starts = episode_starts.astype(bool).T.copy()  # (N, T), slot-major
    starts[:, :: max_length or steps] = True
    flat = starts.reshape(-1)
    sequence = np.cumsum(flat) - 1
    first = np.flatnonzero(flat)
    lengths = np.diff(np.append(first, flat.size))
    position = np.arange(flat.size) - first[sequence]
    return SequenceLayout(sequence, position, lengths, first // steps, first % steps)


class RecurrentRolloutBuffer(RolloutBuffer):
    """SB3's ``RolloutBuffer`` plus the hidden states each step started from, served as sequence minibatches.

    Arguments are those of :class:`~stable_baselines3.common.buffers.RolloutBuffer`; ``max_sequence_length`` cuts the
    sequences (see :func:`sequence_layout`); ``team_sizes`` (the slots' teams, in slot order) makes every minibatch
    hold whole teams, for a policy whose agents send messages.
    """

    max_sequence_length: int | None = None
    team_sizes: Sequence[int] | None = None

    def reset(self) -> None:
        super().reset()
        self.step_states: list[RecurrentStates] = []

    def add_states(self, states: RecurrentStates) -> None:
        """Store the states (already reset where an episode starts) from which the slots act at the next ``add``."""
        self.step_states.append(states)

    def sequence_batches(self, batch_size: int) -> Generator[SequenceBatch, None, None]:
        """Minibatches of whole sequences in random order, each about ``batch_size`` steps (at least one sequence).

        A sequence is the steps of one slot from the rollout's start, an episode start or a multiple of
        ``max_sequence_length`` to the step before the next one, so no minibatch row mixes slots or episodes. It is
        replayed from the states stored for its first step. With :attr:`team_sizes` the sequences of a team's slots
        (which start and end together: a team's agents start their episodes together) go into one minibatch, which
        names each sequence's neighbours' columns.
        """
        assert self.full and len(self.step_states) == self.buffer_size, "fill the buffer (and its states) first"
        layout = sequence_layout(self.episode_starts, self.max_sequence_length)
        count, longest = len(layout.lengths), int(layout.lengths.max())
        mask = np.zeros((longest, count), dtype=bool)
        mask[layout.position, layout.sequence] = True

        def padded(array: np.ndarray) -> th.Tensor:
            flat = array.swapaxes(0, 1).reshape(self.n_envs * self.buffer_size, *array.shape[2:])
            out = np.zeros((longest, count, *array.shape[2:]), dtype=np.float32)
            out[layout.position, layout.sequence] = flat
            return self.to_torch(out)

        observations, actions = padded(self.observations), padded(self.actions)
        values, log_probs = padded(self.values), padded(self.log_probs)
        advantages, returns = padded(self.advantages), padded(self.returns)
        steps, slots = (th.as_tensor(index, device=self.device) for index in (layout.first_steps, layout.slots))

        def first_states(part: int, component: int) -> th.Tensor:
            history = th.stack([states[part][component] for states in self.step_states])  # (T, 1, N, hidden)
            return history[steps, 0, slots].unsqueeze(0)  # (1, S, hidden)

        pi, vf = (
            tuple(first_states(part, component) for component in range(len(self.step_states[0][part]))) for part in (0, 1)
        )
        messages = th.stack([states.messages for states in self.step_states])[steps, slots]  # (S, M)
        states = RecurrentStates(pi, vf, messages)
        group_of, neighbours = self._groups(layout)
        groups = int(group_of.max()) + 1
        order = np.random.permutation(groups)  # noqa: NPY002 - SB3 seeds numpy's global generator (set_random_seed)
        rank = np.empty(groups, dtype=np.int64)
        rank[order] = np.arange(groups)
        batch_of = (
            np.cumsum(np.bincount(group_of, layout.lengths, groups).astype(np.int64)[order]) - 1
        ) // batch_size  # by rank
        ordered = np.argsort(rank[group_of], kind="stable")  # the sequences, group by group in the drawn order
        for batch in np.unique(batch_of):
            chosen = ordered[batch_of[rank[group_of[ordered]]] == batch]
            rows = int(layout.lengths[chosen].max())
            index = th.as_tensor(chosen, device=self.device)
            columns = None
            if neighbours is not None:
                column_of = np.full(count, -1)
                column_of[chosen] = np.arange(len(chosen))
                columns = th.as_tensor(column_of[neighbours[chosen]], device=self.device)
            yield SequenceBatch(
                observations[:rows, index],
                actions[:rows, index],
                values[:rows, index],
                log_probs[:rows, index],
                advantages[:rows, index],
                returns[:rows, index],
                self.to_torch(mask[:rows, chosen]).bool(),
                states.select(index),
                columns,
            )

    def _groups(self, layout: SequenceLayout) -> tuple[np.ndarray, np.ndarray | None]:
        """The group of each sequence, whose sequences go into a minibatch together (each its own, or with
        :attr:`team_sizes` one per team and first step), and each sequence's ring neighbours' sequences (``None``
        without :attr:`team_sizes`)."""
        count = len(layout.lengths)
        if self.team_sizes is None:
            return np.arange(count), None
        sequence_at = np.full((self.n_envs, self.buffer_size), -1)
        sequence_at[layout.slots, layout.first_steps] = np.arange(count)
        neighbours = sequence_at[ring_rows(self.team_sizes)[layout.slots], layout.first_steps[:, None]]
        assert (neighbours >= 0).all(), "a team's slots must start their episodes together"
        teams = np.repeat(np.arange(len(self.team_sizes)), self.team_sizes)[layout.slots]
        return np.unique(teams * self.buffer_size + layout.first_steps, return_inverse=True)[1], neighbours
