"""Recurrent PPO without sb3-contrib, split as sb3-contrib splits it.

- :mod:`~sb3_formation.sb3.recurrent.policies`: :class:`RecurrentFormationPolicy`, actor 512 dense -> 256 recurrent
  -> 2 (fig. 5.1), critic 512 dense -> 512 recurrent -> 256 dense -> 1 (fig. 5.2); GRU or LSTM cells; tanh
  activations, bounded action mean and fixed sigma as in :class:`~sb3_formation.sb3.policies.FormationPolicy`;
  optionally messages to the ring neighbours, received one step late.
- :mod:`~sb3_formation.sb3.recurrent.buffers`: :class:`RecurrentRolloutBuffer`, SB3's ``RolloutBuffer`` plus the hidden
  states (and messages) each step started from; for training it cuts every slot's rollout into sequences at episode
  starts (and every ``max_sequence_length`` steps), so a sequence never spans two slots or two episodes, and builds
  minibatches of whole sequences (with messages, whole teams' sequences), padded to one length and masked, without a
  Python loop over the sequences.
- :mod:`~sb3_formation.sb3.recurrent.ppo`: :class:`RecurrentFormationPPO`, SB3's ``PPO`` whose rollouts carry the
  hidden states (reset per slot at its episode's start) and whose update replays each sequence from its stored
  starting state.
"""

from sb3_formation.sb3.recurrent.buffers import RecurrentRolloutBuffer, sequence_layout
from sb3_formation.sb3.recurrent.policies import (
    CELLS,
    DEFAULT_MAX_SEQUENCE_LENGTH,
    MAX_MESSAGE_SIZE,
    RecurrentFormationPolicy,
    RecurrentStates,
)
from sb3_formation.sb3.recurrent.ppo import RecurrentFormationPPO

__all__ = [
    "CELLS",
    "DEFAULT_MAX_SEQUENCE_LENGTH",
    "MAX_MESSAGE_SIZE",
    "RecurrentFormationPPO",
    "RecurrentFormationPolicy",
    "RecurrentRolloutBuffer",
    "RecurrentStates",
    "sequence_layout",
]
