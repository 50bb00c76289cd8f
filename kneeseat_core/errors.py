"""The error tree: one root, one subclass per failure a user can fix.

Every message says what failed, where (file, key, angle) and how to fix it. Only
`kneeseat_core.cli.main.main` and ROS node callbacks catch these; bugs crash loudly.
"""
from __future__ import annotations

__all__ = ['KneeseatError', 'MeshError', 'ConfigError', 'UsageError', 'SettleError',
           'NoContactError', 'TableError', 'OutOfRangeError', 'NonFiniteError']


class KneeseatError(Exception):
    """Root of every error a user can act on."""


class MeshError(KneeseatError):
    """A mesh file is missing, unreadable, empty, or has invalid coordinates."""


class ConfigError(KneeseatError):
    """A knee configuration or a parameter is invalid; the message names the key."""


class UsageError(KneeseatError):
    """A command-line value or a file it names cannot be used (e.g. a START.json)."""


class SettleError(KneeseatError):
    """A settle cannot start (e.g. the start pose is buried too deep to back out)."""


class NoContactError(SettleError):
    """The moving body never touches the fixed one along the push direction."""

    def __init__(self, travel_m: float) -> None:
        super().__init__(
            f'no contact within {travel_m * 1e3:.1f} mm of travel along the push direction; '
            'check --push (it points from the moving body towards the fixed one) and --start')
        self.travel_m = travel_m


class TableError(KneeseatError):
    """A table file is missing, corrupt, of an unknown schema, or built from other meshes."""


class OutOfRangeError(KneeseatError):
    """A requested attitude lies outside the table grid (and out_of_range is 'drop')."""

    def __init__(self, name: str, value_rad: float, lo_rad: float, hi_rad: float) -> None:
        super().__init__(
            f'{name}={value_rad:.4f} rad outside table [{lo_rad:.4f}, {hi_rad:.4f}] rad; '
            're-run `kneeseat build` with a wider grid or use out_of_range=clamp')
        self.name, self.value_rad, self.lo_rad, self.hi_rad = name, value_rad, lo_rad, hi_rad


class NonFiniteError(KneeseatError):
    """A requested attitude is NaN or infinite."""
