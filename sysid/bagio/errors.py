"""Errors and warnings of the bag reader/writer.

Reading failures raise :class:`sim_core.errors.BagReadError` (re-exported here). Writing has two
classes of its own, both in the thinshell hierarchy so that ``except ThinShellError`` catches them:

- :class:`BagExistsError` (``ConfigError`` and ``FileExistsError``): the output directory exists
  and is not empty, and ``force`` was not given. It is a configuration mistake of the caller, and
  code that already handles ``FileExistsError`` keeps working.
- :class:`BagWriteError`: a write that cannot be done (bag closed, topic re-used with another type,
  type unknown to the ROS 2 Jazzy type store).

Recoverable oddities of a recording (NaN samples dropped, stamps re-sorted, a topic missing) are
reported with :class:`BagWarning` through the ``warnings`` module, never through ``logging``, so
callers can capture them (``warnings.catch_warnings``) or turn them into errors
(``-W error::sysid.bagio.errors.BagWarning``); the reader also keeps their text in
``BagContents.notes``.
"""

from __future__ import annotations

from sim_core.errors import BagReadError, ConfigError, ThinShellError

__all__ = ["BagExistsError", "BagReadError", "BagWarning", "BagWriteError"]


class BagExistsError(ConfigError, FileExistsError):
    """The output bag directory exists and is not empty (pass ``force=True`` to replace it)."""


class BagWriteError(ThinShellError):
    """A message cannot be written (bag closed, topic type clash, unknown message type)."""


class BagWarning(UserWarning):
    """A recording was read with a repair or a gap (NaN samples, unsorted stamps, missing topic)."""
