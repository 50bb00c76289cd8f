"""The types are checked as part of the test run: mypy --strict (mypy.ini)."""
from __future__ import annotations

from pathlib import Path
import subprocess
import sys

from conftest import REPO


def mypy(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, '-m', 'mypy', '--config-file', str(REPO / 'mypy.ini'),
                           *args], cwd=cwd, capture_output=True, text=True)


def test_mypy_is_clean() -> None:
    out = mypy('kneeseat_core', 'kneeseat_ros')
    assert out.returncode == 0, out.stdout + out.stderr


def test_the_core_is_strict_and_only_the_ros_layer_may_call_unannotated_code(
        tmp_path: Path) -> None:
    """An unannotated function is an error in both packages; calling one from annotated
    code is an error in the core and allowed in the ROS layer (whose ROS wheels have no
    annotations)."""
    for package in ('kneeseat_core', 'kneeseat_ros'):
        (tmp_path / package).mkdir()
        (tmp_path / package / '__init__.py').write_text('')
        (tmp_path / package / 'untyped.py').write_text('def twice(x):\n    return 2 * x\n')
        (tmp_path / package / 'caller.py').write_text(
            'from .helper import twice\n\n\ndef four() -> int:\n    return int(twice(2))\n')
        (tmp_path / package / 'helper.py').write_text(
            'def twice(x):  # type: ignore[no-untyped-def]\n    return 2 * x\n')
    for package in ('kneeseat_core', 'kneeseat_ros'):
        untyped = mypy('--no-incremental', f'{package}/untyped.py', cwd=tmp_path)
        assert untyped.returncode == 1 and 'missing a type annotation' in untyped.stdout
    core = mypy('--no-incremental', 'kneeseat_core/caller.py', cwd=tmp_path)
    assert core.returncode == 1 and 'untyped function' in core.stdout
    ros = mypy('--no-incremental', 'kneeseat_ros/caller.py', cwd=tmp_path)
    assert ros.returncode == 0, ros.stdout
