"""`kneeseat` command line: settle, info, lookup, export, plot, render, kinematics, build,
synth, verify.

One module per family of commands, each adding its parsers with `register_command(s)`:
`settle_command` (settle), `table_commands` (info, lookup, export, plot, render,
kinematics), `build_command` (build, synth), `verify_command` (verify). Each handler takes
the parsed arguments and returns the exit code. Errors a user can fix print one line on
stderr and exit non-zero (no traceback unless --debug); `kneeseat settle`'s exit codes are
part of its contract (docs/design.md). A command module imports what only its handlers use
(trimesh, python-fcl, matplotlib, Dask: seconds of start-up) inside them, so that `kneeseat
--help` and the table commands start without it.
"""
from __future__ import annotations

import argparse
from contextlib import contextmanager
import logging
import os
import sys
from typing import Callable, Iterator, Sequence

from threadpoolctl import threadpool_limits

from kneeseat_core.args import EXIT_BAD_INPUT, EXIT_ERROR, join_negative_values, OneLineParser
from kneeseat_core.errors import KneeseatError
from . import build_command, settle_command, table_commands, verify_command

__all__ = ['main', 'build_parser']

log = logging.getLogger('kneeseat')

# Options whose value may start with a minus (`--push -1,0,0`), over every subcommand.
_VALUE_FLAGS = {'--push', '--flexion-deg', '--varus-deg', '--rotation-step',
                '--rotation-resolution', '--step', '--resolution', '--flexion-grid',
                '--varus-grid', '--tibia-point', '--patella-point', '--angles'}


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of `kneeseat` (subcommands register their handler as `command`)."""
    parser = OneLineParser(
        prog='kneeseat', description='Settle rigid bones by collision detection '
        '(US 6,708,142), build pose tables over a range of motion, inspect them.')
    parser.add_argument('--debug', action='store_true', help='show tracebacks')
    parser.add_argument('-v', '--verbose', action='count', default=0,
                        help='more log output (-v info, -vv debug)')
    sub = parser.add_subparsers(dest='name', required=True, metavar='COMMAND',
                                parser_class=OneLineParser)
    settle_command.register_command(sub)
    table_commands.register_commands(sub)
    build_command.register_commands(sub)
    verify_command.register_command(sub)
    return parser


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """OpenBLAS kept to one thread while a command runs, unless the user set
    OPENBLAS_NUM_THREADS: this process's through threadpoolctl, and the workers it spawns
    through that variable, which their OpenBLAS reads as it loads, so that it starts no
    thread to spin idle on a core the workers share (2-3 % of a build's CPU, sampled). The
    variable is taken away again when the command ends. Run as a program, the variable is
    set already, before numpy loaded (`kneeseat_core.console`)."""
    if 'OPENBLAS_NUM_THREADS' in os.environ:
        yield
        return
    os.environ['OPENBLAS_NUM_THREADS'] = '1'
    try:
        with threadpool_limits(limits=1, user_api='blas'):
            yield
    finally:
        os.environ.pop('OPENBLAS_NUM_THREADS', None)


def main(argv: Sequence[str] | None = None) -> int:
    """The command line on `argv` (default: `sys.argv`); returns the exit code
    (`kneeseat_core.console.run` runs it as the `kneeseat` program)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    try:
        args = parser.parse_args(join_negative_values(argv, _VALUE_FLAGS))
    except SystemExit as exit_:           # argparse already printed its one-line usage error
        return int(exit_.code or 0) and EXIT_BAD_INPUT
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format='kneeseat: %(levelname)s: %(message)s')
    logging.getLogger('trimesh').setLevel(max(level, logging.ERROR))
    command: Callable[[argparse.Namespace], int] = args.command
    try:
        with one_blas_thread():
            return command(args)
    except KneeseatError as err:
        if args.debug:
            raise
        print(f'kneeseat {args.name}: error: {err}', file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as err:
        if args.debug:
            raise
        print(f'kneeseat {args.name}: error: {err}', file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print(f'kneeseat {args.name}: interrupted', file=sys.stderr)
        return 130
