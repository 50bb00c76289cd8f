"""`colcon build` gives the ament_python layout that `ros2 run kneeseat_ros table_server` uses.

The package sources are copied into a temporary colcon workspace and built with the venv's
colcon (colcon-common-extensions from PyPI); the installed table_server is then started
from the install tree (PYTHONPATH = the install's site-packages) and must answer a message.
`pip install --prefix` would put the scripts in bin/, which `ros2 run` does not search.
"""
from __future__ import annotations

from collections.abc import Iterator
import os
from pathlib import Path
import shutil
import subprocess
import sys
from typing import Any

from conftest import REPO, write_synthetic_table
import pytest
from test_table_server import assert_answer, Probe, ServerProcess

from kneeseat_core.table import read_table
from kneeseat_ros.conversions import joint_state

pytestmark = pytest.mark.ros

SOURCES = ('package.xml', 'setup.py', 'setup.cfg', 'resource', 'kneeseat_core',
           'kneeseat_ros', 'config')
COLCON = Path(sys.prefix) / 'bin' / 'colcon'
PY = f'python{sys.version_info.major}.{sys.version_info.minor}'


@pytest.fixture(scope='module')
def install(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """Build the package once with colcon; yields install/kneeseat_ros."""
    if not COLCON.exists():
        pytest.fail(f'{COLCON} missing: run ./scripts/setup (requirements/dev.txt has '
                    'colcon-common-extensions)')
    ws = tmp_path_factory.mktemp('ws')
    src = ws / 'src' / 'kneeseat_ros'
    src.mkdir(parents=True)
    ignore = shutil.ignore_patterns('__pycache__', '*.pyc', '*.egg-info')
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, src / name, ignore=ignore)
        else:
            shutil.copy2(REPO / name, src / name)
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE='1')
    done = subprocess.run([str(COLCON), 'build', '--base-paths', 'src'], cwd=ws, env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f'colcon build failed:\n{done.stdout}\n{done.stderr}'
    yield ws / 'install' / 'kneeseat_ros'


def install_env(prefix: Path) -> dict[str, str]:
    """What `source install/setup.bash` would set, on top of the venv's ROS wheels."""
    site = prefix / 'lib' / PY / 'site-packages'
    env = dict(os.environ)
    env['PYTHONPATH'] = os.pathsep.join([str(site), *filter(None, [env.get('PYTHONPATH')])])
    env['AMENT_PREFIX_PATH'] = os.pathsep.join([str(prefix), sys.prefix])
    return env


def test_colcon_gives_the_ament_layout(install: Path) -> None:
    for rel in ('lib/kneeseat_ros/table_server',
                'share/ament_index/resource_index/packages/kneeseat_ros',
                'share/kneeseat_ros/package.xml',
                'share/kneeseat_ros/config/table_server.yaml'):
        assert (install / rel).is_file(), f'{rel} missing from {install}'
    assert os.access(install / 'lib/kneeseat_ros/table_server', os.X_OK)
    # what `ros2 run` does: find the package prefix in the ament index, then lib/<pkg>/<exe>;
    # and the installed modules, not the source tree, are the ones imported
    code = ('import ament_index_python.packages as p, kneeseat_ros.table_server as t; '
            "print(p.get_package_prefix('kneeseat_ros')); print(t.__file__)")
    out = subprocess.run([sys.executable, '-c', code], env=install_env(install), cwd='/',
                         capture_output=True, text=True, check=True).stdout.split()
    assert Path(out[0]) == install
    assert Path(out[1]).is_relative_to(install), out[1]


def test_installed_table_server_answers(install: Path, tmp_path: Path, domain_id: int,
                                        context: Any) -> None:
    table_path = write_synthetic_table(tmp_path / 'knee.npz', seed=4)
    table = read_table(table_path)
    params = install / 'share/kneeseat_ros/config/table_server.yaml'
    srv = ServerProcess(tmp_path, domain_id, table_path,
                        executable=install / 'lib/kneeseat_ros/table_server',
                        env=install_env(install), ros_args=['--params-file', str(params)])
    probe = Probe(context)
    try:
        probe.wait_connected()
        msg = joint_state(-0.9, 0.03, probe.next_stamp())
        assert_answer(table, msg, probe.ask(msg))
    finally:
        probe.destroy()
        srv.stop_clean()
