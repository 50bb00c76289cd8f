"""The `kneeseat` console script and `python -m kneeseat_core`: the command line
(`kneeseat_core.cli.main`) run as a program."""
from __future__ import annotations

import gc
import os
import sys

__all__ = ['run']


def run() -> None:
    """Run the command line on `sys.argv` and exit with its code.

    OpenBLAS reads its thread count once, when numpy loads it: the command line keeps it
    to one thread (`kneeseat_core.cli.main.one_blas_thread`), and the variable is set here,
    before the command line's modules load numpy, so that neither this process nor the
    workers forked from it start a thread that spins on a core the workers share (unless
    the user set it). When the command is done the objects left are frozen (`gc.freeze`):
    the interpreter's shutdown then leaves them out of its collections, which took 0.2 s
    after a build (trimesh, scipy and the scene loaded) and take 0.06 s so; every exit
    handler still runs.
    """
    os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
    from kneeseat_core.cli.main import main
    code = main()
    gc.freeze()
    sys.exit(code)
