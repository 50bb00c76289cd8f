"""The code is linted as ament_flake8 would (settings in .flake8), and the core stays ROS-free."""
from __future__ import annotations

import subprocess
import sys

from conftest import REPO


def test_flake8_is_clean() -> None:
    out = subprocess.run([sys.executable, '-m', 'flake8', 'kneeseat_core', 'kneeseat_ros',
                          'test', 'benchmarks'], cwd=REPO, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


def test_core_does_not_import_ros() -> None:
    code = ('import sys, kneeseat_core.cli.main, kneeseat_core.sweep.build, '
            'kneeseat_core.report.plots, kneeseat_core.sweep.cluster; '
            'print(sorted(m for m in sys.modules if m.split(".")[0] in '
            '("rclpy", "mcap", "mcap_ros2", "geometry_msgs", "sensor_msgs")))')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True, cwd=REPO)
    assert out.stdout.strip() == '[]'
