"""The `kneeseat` command line (`main`): one module per family of commands.

The command line runs its work in worker processes, so it keeps OpenBLAS to one thread,
set before numpy loads: the workers it spawns inherit it, and no BLAS thread is started to
spin idle on a core the workers share (2-3 % of a build's CPU, sampled). A chain also limits
BLAS itself, for other callers (`kneeseat_core.sweep.chains`). A value the user set stands.
"""
import os

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

from .main import build_parser, main  # noqa: E402 - after the thread limit, before numpy

__all__ = ['main', 'build_parser']
