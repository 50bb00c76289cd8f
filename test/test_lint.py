"""The code is linted as ament_flake8 would (settings in .flake8); the layering rules are in
test_layers.py."""
from __future__ import annotations

import subprocess
import sys

from conftest import REPO


def test_flake8_is_clean() -> None:
    out = subprocess.run([sys.executable, '-m', 'flake8', 'kneeseat_core', 'kneeseat_ros',
                          'test', 'benchmarks'], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr
