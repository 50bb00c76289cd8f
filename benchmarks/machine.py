"""The one-line machine description every benchmark prints (shared by the scripts here)."""
from __future__ import annotations

import os
from pathlib import Path
import platform

__all__ = ['cpu_model', 'load_average', 'describe_machine']


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
