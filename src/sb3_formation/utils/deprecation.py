"""Old spellings kept for one release: each warns, naming its replacement (``CHANGELOG.md`` lists them all)."""

from __future__ import annotations

import warnings


def warn_renamed(old: str, new: str, stacklevel: int = 3) -> None:
    """Warn that ``old`` is deprecated in favour of ``new``.

    A ``FutureWarning``, which Python shows by default (a ``DeprecationWarning`` is hidden outside ``__main__``), as
    pandas and scikit-learn do for changes their users must act on.

    :param old: the old spelling, as the user wrote it (``--preset``, ``FormationConfig.preset``)
    :param new: what to write instead
    :param stacklevel: the frame the warning names (3: the caller of the function that warns)
    """
    warnings.warn(f"{old} is deprecated and will be removed in the next release; use {new}", FutureWarning, stacklevel)
