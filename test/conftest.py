"""Shared test helpers: ROS environment, rclpy contexts, waiting with deadlines, tables.

Import helpers with `from conftest import spin_until, ros_env, synthetic_table` (pytest puts
this directory on sys.path). ROS tests get their own ROS_DOMAIN_ID per test, discovery
limited to this machine, and AMENT_PREFIX_PATH including the venv (the ROS wheels keep their
ament index there), so plain `python -m pytest` works without sourcing scripts/env.sh.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
import itertools
import os
from pathlib import Path
import sys
import time
from typing import Any

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / 'shared' / 'data'
_DOMAIN_COUNTER = itertools.count()


def next_domain_id() -> int:
    """A ROS_DOMAIN_ID in 1..100, different for each call in this process (pid-seeded)."""
    return (os.getpid() * 7 + 37 * next(_DOMAIN_COUNTER)) % 100 + 1


def ros_env(domain_id: int, base: dict[str, str] | None = None) -> dict[str, str]:
    """Environment for a ROS process: own domain, localhost discovery, venv ament index."""
    env = dict(os.environ if base is None else base)
    prefixes = [p for p in env.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    if sys.prefix not in prefixes:
        prefixes.insert(0, sys.prefix)
    env.update(ROS_DOMAIN_ID=str(domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST',
               AMENT_PREFIX_PATH=os.pathsep.join(prefixes), PYTHONUNBUFFERED='1')
    env.pop('ROS_LOCALHOST_ONLY', None)
    return env


@pytest.fixture
def domain_id(monkeypatch: pytest.MonkeyPatch) -> int:
    """A fresh ROS_DOMAIN_ID, also set in this process's environment for rclpy.init."""
    did = next_domain_id()
    for key, value in ros_env(did).items():
        if os.environ.get(key) != value:
            monkeypatch.setenv(key, value)
    return did


@pytest.fixture
def context(domain_id: int) -> Iterator[Any]:
    """A separate rclpy Context on the test's own domain, shut down afterwards."""
    import rclpy
    from rclpy.context import Context
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    yield ctx
    rclpy.try_shutdown(context=ctx)


def spin_until(executor: Any, done: Callable[[], bool], timeout_s: float = 10.0,
               what: str = 'condition', every: Callable[[], None] | None = None) -> None:
    """Spin `executor` until `done()` is true; fail the test after `timeout_s`.

    Args:
        every: optional action run before each spin (e.g. re-publish until answered).
    """
    deadline = time.monotonic() + timeout_s
    while not done():
        if time.monotonic() > deadline:
            pytest.fail(f'{what} not met within {timeout_s} s')
        if every is not None:
            every()
        executor.spin_once(timeout_sec=0.02)


def synthetic_table(seed: int = 0, bodies: tuple[str, ...] = ('tibia', 'patella'),
                    flexion_deg: tuple[float, float, int] = (-90.0, 0.0, 19),
                    varus_deg: tuple[float, float, int] = (-10.0, 10.0, 5),
                    offset_m: float = 0.0, mesh_dir: Path | None = None) -> Any:
    """A PoseTable on a uniform grid with smooth, seeded poses (TKA axes, frame 'femur').

    Orientation of body b at (f, v) = axes.orientation(f, v, r) with a smooth screw-home r
    plus seeded noise; positions smooth plus noise (m) and `offset_m` on x (to tell tables
    apart). Two cells of the last body are marked not converged.
    """
    from kneeseat_core.geometry import KneeAxes, quat_from_matrix
    from kneeseat_core.table import PoseTable, SCHEMA
    rng = np.random.default_rng(seed)
    axes = KneeAxes.from_vectors([0, 0, 1], [1, 0, 0], [0, 1, 0])
    flexion = np.radians(np.linspace(*flexion_deg))
    varus = np.radians(np.linspace(*varus_deg))
    f, v = np.meshgrid(flexion, varus, indexing='ij')                      # (F, V)
    n = len(bodies)
    rotation = 0.2 * np.sin(f)[None] + rng.normal(0.0, 0.02, (n, *f.shape))  # (B, F, V)
    quat = quat_from_matrix(axes.orientation(np.broadcast_to(f, rotation.shape).ravel(),
                                             np.broadcast_to(v, rotation.shape).ravel(),
                                             rotation.ravel())).reshape(n, *f.shape, 4)
    position = np.stack([0.01 * np.sin(f) + offset_m, -0.005 * np.cos(f), 0.02 * v], -1)
    position = position[None] + rng.normal(0.0, 1e-3, (n, *f.shape, 3))
    converged = np.ones((n, *f.shape), dtype=bool)
    converged[-1, 1, 1] = converged[-1, -2, -1] = False
    mesh = (lambda name: str(mesh_dir / f'{name}.stl')) if mesh_dir else (lambda name: None)
    metadata = {
        'schema': SCHEMA, 'kneeseat_version': 'test',
        'reference': {'name': 'femur', 'frame': 'femur', 'mesh': mesh('femur'),
                      'mesh_sha256': ''},
        'bodies': [{'name': b, 'frame': b, 'mesh': mesh(b), 'mesh_sha256': '',
                    'display_mesh': None} for b in bodies],
        'axes': {'flexion': [0.0, 0.0, 1.0], 'varus': [1.0, 0.0, 0.0],
                 'long': [0.0, 1.0, 0.0]},
        'config': {}, 'settle': {}, 'arrays_sha256': '', 'built': '2025-01-01T00:00:00Z',
        'summary': {'cells': int(converged.size), 'converged': int(converged.sum()),
                    'wall_s': 0.0, 'collision_checks': 0},
    }
    return PoseTable(flexion, varus, position, quat, converged,
                     rng.integers(1, 50, converged.shape), metadata)


def write_synthetic_table(path: Path, **kwargs: Any) -> Path:
    """Write `synthetic_table(**kwargs)` to `path` with the core's writer; returns path."""
    from kneeseat_core.table import write_table
    write_table(path, synthetic_table(**kwargs))
    return path
