"""The ROS layer's errors: every one a `KneeseatError` (kneeseat_core.errors' tree).

Every message says what failed, where (file, topic, option) and how to fix it. The node's
callbacks and the command-line entry points catch these; bugs crash loudly. `CdrError` is
also a `ValueError` (what it was before it joined the tree), so a caller that catches
ValueError around CDR decoding still catches it.
"""
from __future__ import annotations

from kneeseat_core.errors import KneeseatError

__all__ = ['BadInputError', 'RecorderError', 'MessageTypeError', 'BagError', 'TrajectoryError',
           'DemoError', 'DataMissing', 'CdrError']


class BadInputError(KneeseatError):
    """An input message cannot be turned into an attitude; `reason` names the diagnostics
    counter it goes to (one of `conversions.DROP_REASONS`)."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


class RecorderError(KneeseatError):
    """A bag directory cannot be created or written, or a topic cannot be recorded."""


class MessageTypeError(KneeseatError):
    """A message type name is malformed or its interface package is not installed."""


class BagError(KneeseatError):
    """A path is not a readable ros2 MCAP bag, or holds none of the requested topics."""


class TrajectoryError(KneeseatError):
    """An angle CSV or a trajectory request is invalid; the message names the line/option."""


class DemoError(KneeseatError):
    """A demo phase failed; the message says which one and what to look at."""


class DataMissing(KneeseatError):
    """The chosen knee's meshes are not where its config says (the demo exits with 2)."""


class CdrError(KneeseatError, ValueError):
    """Bytes that are not a little-endian CDR message of the expected type.

    The node catches it in its input callbacks (`responder`): it falls back to rclpy's
    deserialiser, and counts the message as malformed only when that fails too. A
    `ValueError` as well, for callers that catch that around decoding.
    """
