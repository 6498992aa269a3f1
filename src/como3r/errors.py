"""The one exception hierarchy of como3r.

Every error that a user can cause (bad input, bad configuration, a bad checkpoint) is a
``Como3rError``; the command line prints its message on one line and exits non-zero.
Errors that indicate a bug in como3r are left as ordinary Python exceptions.
"""

from __future__ import annotations


class Como3rError(Exception):
    """Base class of every error como3r raises on purpose."""


class ConfigError(Como3rError):
    """An invalid configuration file, key or value."""


class InputError(Como3rError):
    """Invalid user input: a missing, empty, unreadable or malformed file or folder."""


class GeometryError(Como3rError):
    """A geometric computation that cannot be carried out (degenerate input)."""


class CheckpointError(Como3rError):
    """A model checkpoint or codebook that cannot be loaded safely."""


class PriorError(Como3rError):
    """A prior that cannot produce a prediction for the given views."""


class TrackingError(Como3rError):
    """Tracking of a frame failed (too few matches, non-finite values, failed solve)."""


class SolverError(Como3rError):
    """A non-linear least-squares solve that failed."""


class StoreError(Como3rError):
    """A session store that cannot be read: not a store, corrupted, inconsistent, or written
    in a format version this como3r does not read."""


class MessageError(Como3rError):
    """A message that cannot be encoded, or bytes that are not a valid message."""
