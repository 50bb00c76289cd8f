"""The one-line machine description every benchmark prints, and the measuring helpers the
scripts here share (process CPU time, a per-call timing loop)."""
from __future__ import annotations

from collections.abc import Callable
import os
from pathlib import Path
import platform
import time
from typing import Any

__all__ = ['cpu_model', 'load_average', 'describe_machine', 'cpu_seconds', 'call_times_us']


def cpu_model() -> str:
    """The CPU model name from /proc/cpuinfo, or the platform's guess."""
    try:
        for line in Path('/proc/cpuinfo').read_text().splitlines():
            if line.startswith('model name'):
                return line.split(':', 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def load_average() -> str:
    """The 1, 5 and 15 minute load averages ('n/a' where the OS has none)."""
    if not hasattr(os, 'getloadavg'):
        return 'n/a'
    return ', '.join(f'{v:.2f}' for v in os.getloadavg())


def describe_machine() -> str:
    """Platform, CPU model, usable cores, load average and Python version."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else os.cpu_count()
    return (f'machine: {platform.platform()}; {cpu_model()}; {cores} usable CPUs; '
            f'load average {load_average()}; Python {platform.python_version()}')


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process (s) from /proc/<pid>/stat."""
    fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


def call_times_us(fn: Callable[[], Any], n: int, runs: int) -> list[float]:
    """The mean time (us) of `fn()` over `n` calls, for each of `runs` runs."""
    out = []
    for _ in range(runs):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        out.append((time.perf_counter() - t0) / n * 1e6)
    return out
