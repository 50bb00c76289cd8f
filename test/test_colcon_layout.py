"""`colcon build` gives the ament_python layout that `ros2 run kneeseat_ros table_server` uses.

The package sources are copied into a temporary colcon workspace and built with the venv's
colcon (colcon-common-extensions from PyPI); the installed table_server is then started
from the install tree (PYTHONPATH = the install's site-packages) and must answer a message.
`pip install --prefix` would put the scripts in bin/, which `ros2 run` does not search.
"""
from __future__ import annotations

import os
from pathlib import Path
import subprocess
import sys
from typing import Any

from conftest import install_env, write_synthetic_table
import pytest
from ros_helpers import assert_answer, Probe, ServerProcess

from kneeseat_core.table import read_table
from kneeseat_ros.conversions import joint_state

pytestmark = pytest.mark.ros


@pytest.fixture(scope='module')
def install(colcon_install: Path) -> Path:
    """install/kneeseat_ros of the session's colcon build (conftest.colcon_install)."""
    return colcon_install


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
