"""Command-line pieces every kneeseat tool shares: value types, one-line errors, exit codes.

`join_negative_values` lets a value start with a minus (`--push -1,0,0`): argparse would
take `-1,0,0` for an option; joined into `--push=-1,0,0` it is a value.
"""
from __future__ import annotations

import argparse
from collections.abc import Iterable, Sequence
import math
import os
from typing import NoReturn, TYPE_CHECKING

__all__ = ['EXIT_OK', 'EXIT_ERROR', 'EXIT_BAD_INPUT', 'EXIT_NOT_CONVERGED',
           'EXIT_NO_CONTACT', 'OneLineParser', 'vector3', 'angles', 'join_negative_values',
           'default_workers', 'worker_count', 'MOST_WORKERS_PER_CORE']

EXIT_OK, EXIT_ERROR, EXIT_BAD_INPUT, EXIT_NOT_CONVERGED, EXIT_NO_CONTACT = 0, 1, 2, 3, 4

if TYPE_CHECKING:       # what `add_subparsers` returns; the class is private to argparse
    Subcommands = argparse._SubParsersAction['OneLineParser']


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line (no usage block) and exit 2."""

    def error(self, message: str) -> NoReturn:
        """Print `prog: error: message; see --help` and exit with EXIT_BAD_INPUT."""
        self.exit(EXIT_BAD_INPUT, f'{self.prog}: error: {message}; see --help\n')


def vector3(text: str) -> tuple[float, float, float]:
    """Parse 'x,y,z' (also 'x y z'); argparse reports failures as usage errors."""
    parts = text.replace(',', ' ').split()
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not three numbers like 0,-1,0") from None
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"'{text}' is not three finite numbers like 0,-1,0")
    return values[0], values[1], values[2]


def angles(text: str) -> list[float]:
    """Parse '0,-30,-60' degrees."""
    try:
        values = [float(p) for p in text.replace(',', ' ').split()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a list of numbers like 0,-45,-90") \
            from None
    if not values or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"'{text}' is not a list of finite numbers")
    return values


def join_negative_values(argv: Sequence[str], flags: Iterable[str]) -> list[str]:
    """Join `--push -1,0,0` into `--push=-1,0,0` for each of `flags` whose value starts with
    a minus followed by a digit or a point, so that argparse does not take it for an option.
    """
    wanted = set(flags)
    out: list[str] = []
    i = 0
    while i < len(argv):
        arg = argv[i]
        if arg in wanted and i + 1 < len(argv) and argv[i + 1].startswith('-') \
                and len(argv[i + 1]) > 1 and (argv[i + 1][1].isdigit() or argv[i + 1][1] == '.'):
            out.append(f'{arg}={argv[i + 1]}')
            i += 2
            continue
        out.append(arg)
        i += 1
    return out


def default_workers() -> int:
    """All cores this process may use: the default of every `--workers` option."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


# a local pool of more workers than this many a usable core only makes them contend (and a
# mistyped count of thousands would fork as many processes at its first chain)
MOST_WORKERS_PER_CORE = 4


def worker_count(text: str) -> int:
    """Parse a `--workers` value: a whole number from 1 to `MOST_WORKERS_PER_CORE` times the
    cores this process may use; argparse reports failures as usage errors."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number of worker "
                                         'processes') from None
    most = MOST_WORKERS_PER_CORE * default_workers()
    if not 1 <= value <= most:
        raise argparse.ArgumentTypeError(
            f'{value} worker processes: give 1 to {most} ({MOST_WORKERS_PER_CORE} per core of '
            f'the {default_workers()} this process may use)')
    return value
