"""Shared test helpers: ROS environment, rclpy contexts, waiting with deadlines, tables.

Import helpers with `from conftest import spin_until, ros_env, synthetic_table` (pytest puts
this directory on sys.path). ROS tests get their own ROS_DOMAIN_ID per test, discovery
limited to this machine, and AMENT_PREFIX_PATH including the venv (the ROS wheels keep their
ament index there), so plain `python -m pytest` works without sourcing scripts/env.sh.
`synthetic_table` is the one builder of synthetic pose tables: the grid, bodies, pose
model, converged flags, statuses and metadata are its parameters.
"""
from __future__ import annotations

from collections.abc import Callable, Generator, Iterable, Iterator, Mapping, Sequence
import fcntl
import hashlib
import itertools
import os
from pathlib import Path
import shutil
import subprocess
import sys
import tempfile
import time
from typing import Any

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / 'shared' / 'data'
# Build/install tools for what PyPI lacks (see README, "The ROS 2 node"): the Jazzy `ros2`
# CLI sources and a colcon build of tf2_msgs against the venv's ROS wheels.
SHARED_TOOLS = REPO.parent / 'shared' / 'tools'
TF2_MSGS_BUILD = SHARED_TOOLS / 'tf2_msgs' / 'build'
ROS2CLI_INSTALL = SHARED_TOOLS / 'ros2cli' / 'install'
_DOMAIN_COUNTER = itertools.count()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]
                              ) -> Generator[None, Any, None]:
    """A failed test that ran a node (`ros_helpers.ServerProcess` writes its stderr to
    server.err under the test's tmp_path) shows that stderr's last lines in its report:
    a failure seen once in CI can then be read without the test's files, which pytest
    removes three runs later."""
    outcome = yield
    report = outcome.get_result()
    tmp = getattr(item, 'funcargs', {}).get('tmp_path')
    if report.failed and report.when == 'call' and isinstance(tmp, Path):
        for err in sorted(tmp.rglob('server.err')):
            lines = err.read_text(errors='replace').splitlines()[-40:]
            report.sections.append((f'node stderr ({err.relative_to(tmp)}, last 40 lines)',
                                    '\n'.join(lines)))


def fcl_object(mesh: Any) -> Any:
    """A python-fcl collision object of `mesh` (a trimesh), built here and not by the
    project, for the tests' own referees; at the identity until `setTransform`."""
    import fcl
    bvh = fcl.BVHModel()
    bvh.beginModel(len(mesh.faces), len(mesh.vertices))     # (triangles, vertices)
    bvh.addSubModel(np.asarray(mesh.vertices, dtype=np.float64),
                    np.asarray(mesh.faces, dtype=np.int64))
    bvh.endModel()
    return fcl.CollisionObject(bvh, fcl.Transform())


def fcl_collides(moving: Any, fixed: Any, pose: Any) -> bool:
    """True if the python-fcl object `moving`, placed at `pose` (4x4, in `fixed`'s frame),
    overlaps `fixed`: a boolean query of the tests' own; leaves `moving` at `pose`."""
    import fcl
    moving.setTransform(fcl.Transform(pose[:3, :3], pose[:3, 3]))
    return fcl.collide(moving, fixed, fcl.CollisionRequest(), fcl.CollisionResult()) > 0


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


# Every long-running child a test starts (servers, replays); reaped after each test, so that
# a test that fails before its own stop never leaves a node running on the machine.
CHILDREN: list[subprocess.Popen[Any]] = []


def track_child(proc: subprocess.Popen[Any]) -> subprocess.Popen[Any]:
    """Register `proc` to be killed at the end of the current test if it still runs."""
    CHILDREN.append(proc)
    return proc


@pytest.fixture(autouse=True)
def reap_children() -> Iterator[None]:
    """Kill and wait for any tracked child still running when a test ends."""
    yield
    while CHILDREN:
        proc = CHILDREN.pop()
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)


@pytest.fixture
def ament_prefix(monkeypatch: pytest.MonkeyPatch) -> None:
    """The ROS wheels keep their ament index (and .msg files) in the venv prefix."""
    paths = os.environ.get('AMENT_PREFIX_PATH', '')
    monkeypatch.setenv('AMENT_PREFIX_PATH', os.pathsep.join(filter(None, [sys.prefix, paths])))


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


# A pose model for `synthetic_table`: (flexion, varus) on the (F, V) grid (rad) and the
# table's seeded rng -> (rotations (B, F, V, 3, 3), positions (B, F, V, 3) m).
PoseModel = Callable[[np.ndarray, np.ndarray, np.random.Generator],
                     tuple[np.ndarray, np.ndarray]]
Cell = tuple[int, int, int]          # (body, flexion index, varus index); negatives from the end
# TKA knee frame: X anterior, Y superior, Z lateral; flexion about Z, varus about X.
TKA_AXES = {'flexion': [0.0, 0.0, 1.0], 'varus': [1.0, 0.0, 0.0], 'long': [0.0, 1.0, 0.0]}


def _smooth_poses(n: int, offset_m: float) -> PoseModel:
    """The default pose model: a smooth screw-home r = 0.2 sin(flexion) plus N(0, 0.02) rad
    noise about the long axis, positions smooth plus N(0, 1 mm) noise, `offset_m` on x."""
    def poses(f: np.ndarray, v: np.ndarray,
              rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        from kneeseat_core.geometry import KneeAxes
        axes = KneeAxes.from_vectors(TKA_AXES['flexion'], TKA_AXES['varus'], TKA_AXES['long'])
        rotation = 0.2 * np.sin(f)[None] + rng.normal(0.0, 0.02, (n, *f.shape))  # (B, F, V)
        rot = axes.orientation(np.broadcast_to(f, rotation.shape).ravel(),
                               np.broadcast_to(v, rotation.shape).ravel(), rotation.ravel())
        position = np.stack([0.01 * np.sin(f) + offset_m, -0.005 * np.cos(f), 0.02 * v], -1)
        position = position[None] + rng.normal(0.0, 1e-3, (n, *f.shape, 3))
        return rot.reshape(n, *f.shape, 3, 3), position
    return poses


def _entry(body: str | Mapping[str, Any], mesh_dir: Path | None,
           moving: bool = True) -> dict[str, Any]:
    """A body's metadata entry: a name gets frame = name, mesh `mesh_dir/<name>.stl` (None
    without `mesh_dir`), no mesh hash and, for a moving body, no display mesh; a mapping is
    merged over that."""
    given = {'name': body} if isinstance(body, str) else dict(body)
    name = given['name']
    default = {'name': name, 'frame': name,
               'mesh': str(mesh_dir / f'{name}.stl') if mesh_dir else None, 'mesh_sha256': ''}
    if moving:
        default['display_mesh'] = None
    return {**default, **given}


def synthetic_table(seed: int = 0,
                    bodies: Sequence[str | Mapping[str, Any]] = ('tibia', 'patella'),
                    flexion_deg: tuple[float, float, int] = (-90.0, 0.0, 19),
                    varus_deg: tuple[float, float, int] = (-10.0, 10.0, 5),
                    offset_m: float = 0.0, mesh_dir: Path | None = None, *,
                    flexion_rad: Any = None, varus_rad: Any = None,
                    poses: PoseModel | None = None,
                    nonconverged: Iterable[Cell] = ((-1, 1, 1), (-1, -2, -1)),
                    statuses: Mapping[Cell, int] | None = None, iterations: int | None = None,
                    reference: str | Mapping[str, Any] = 'femur',
                    meta: Mapping[str, Any] | None = None) -> Any:
    """The tests' one synthetic PoseTable, built from arrays (TKA axes, `TKA_AXES`).

    Args:
        seed: seeds the rng of the pose model (noise) and of the iteration counts.
        bodies: moving bodies, as names or metadata entries (`_entry`), in array order.
        flexion_deg, varus_deg: uniform grids, `np.linspace(start, stop, count)` in degrees;
            `flexion_rad`, `varus_rad` (any ascending arrays, rad) replace them when given.
        offset_m: added to x by the default pose model (to tell tables apart).
        mesh_dir: the default entries' meshes are `mesh_dir/<name>.stl` (else None).
        poses: the pose model (`PoseModel`); default `_smooth_poses`.
        nonconverged: the cells marked not converged (default: two cells of the last body).
        statuses: when given, each cell's settle status is recorded in the metadata
            (`cells`): these codes at these cells, REST at the other converged cells,
            UNKNOWN at the other non-converged ones. A code must agree with the cell's
            converged flag (`kneeseat_core.status.AT_REST`).
        iterations: every cell's iteration count; default seeded in 1..49.
        reference: the fixed body, as a name or a metadata entry (frame = name).
        meta: top-level metadata keys to set or replace (name, config, summary, ...).
    """
    from kneeseat_core.geometry import quat_from_matrix
    from kneeseat_core.status import AT_REST, Status, STATUS_NAMES
    from kneeseat_core.table import PoseTable, SCHEMA
    if poses is not None and offset_m:
        raise ValueError('offset_m is added by the default pose model; shift your own poses')
    rng = np.random.default_rng(seed)
    flexion = np.radians(np.linspace(*flexion_deg)) if flexion_rad is None else \
        np.asarray(flexion_rad, dtype=np.float64)
    varus = np.radians(np.linspace(*varus_deg)) if varus_rad is None else \
        np.asarray(varus_rad, dtype=np.float64)
    f, v = np.meshgrid(flexion, varus, indexing='ij')                      # (F, V)
    n = len(bodies)
    rot, position = (poses or _smooth_poses(n, offset_m))(f, v, rng)
    shape = (n, *f.shape)
    assert rot.shape == (*shape, 3, 3) and position.shape == (*shape, 3), \
        f'pose model gave {rot.shape}, {position.shape} for {shape} cells'
    quat = quat_from_matrix(rot.reshape(-1, 3, 3)).reshape(*shape, 4)
    converged = np.ones(shape, dtype=bool)
    for cell in nonconverged:
        converged[cell] = False
    metadata: dict[str, Any] = {
        'schema': SCHEMA, 'kneeseat_version': 'test',
        'reference': _entry(reference, mesh_dir, moving=False),
        'bodies': [_entry(b, mesh_dir) for b in bodies],
        'axes': {key: list(axis) for key, axis in TKA_AXES.items()},
        'config': {}, 'settle': {}, 'arrays_sha256': '', 'built': '2025-01-01T00:00:00Z',
        'summary': {'cells': int(converged.size), 'converged': int(converged.sum()),
                    'wall_s': 0.0, 'collision_checks': 0},
    }
    if statuses is not None:
        codes = np.where(converged, Status.REST, Status.UNKNOWN)
        for cell, code in statuses.items():
            assert (code in AT_REST) == converged[cell], \
                f'status {code} at {cell} disagrees with converged={converged[cell]}'
            codes[cell] = code
        metadata['cells'] = {'status_names': {str(k): name for k, name in STATUS_NAMES.items()},
                             'status': codes.tolist()}
    metadata.update(meta or {})
    counts = rng.integers(1, 50, shape) if iterations is None else np.full(shape, iterations)
    return PoseTable(flexion, varus, position, quat, converged, counts, metadata)


def pixels_near(path: Path, rgb: Sequence[float], tol: float = 0.1) -> int:
    """How many pixels of the PNG at `path` are within `tol` of colour `rgb` (0..1) in every
    channel (antialiased edges count only where they are close enough)."""
    from matplotlib.image import imread
    image = imread(path)[..., :3]
    return int((np.abs(image - np.asarray(rgb)) < tol).all(axis=-1).sum())


def write_synthetic_table(path: Path, **kwargs: Any) -> Path:
    """Write `synthetic_table(**kwargs)` to `path` with the core's writer; returns path."""
    from kneeseat_core.table import write_table
    write_table(path, synthetic_table(**kwargs))
    return path


def _cache_dir(name: str) -> Path:
    """A per-venv cache folder under the temp dir (kept between runs, locked while built)."""
    tag = hashlib.sha256(sys.prefix.encode()).hexdigest()[:10]
    path = Path(tempfile.gettempdir()) / f'kneeseat-{name}-{tag}'
    path.parent.mkdir(parents=True, exist_ok=True)
    return path


def _locked_run(lock: Path, args: list[str], timeout_s: float) -> subprocess.CompletedProcess:
    with open(lock, 'w') as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        return subprocess.run(args, capture_output=True, text=True, timeout=timeout_s)


@pytest.fixture(scope='session')
def tf2_msgs_env() -> dict[str, str]:
    """Environment with tf2_msgs built by the shared tool (cached per venv; slow once).

    Skips with the reason when the tool, a C/C++ compiler, make or Python.h is missing.
    LD_LIBRARY_PATH must be set before Python starts: use it for subprocesses only.
    """
    import sysconfig
    if not TF2_MSGS_BUILD.is_file():
        pytest.skip(f'tf2_msgs build tool not found at {TF2_MSGS_BUILD}')
    for tool in ('cc', 'c++', 'make'):
        if shutil.which(tool) is None:
            pytest.skip(f'no {tool!r} on PATH: the tf2_msgs build needs a C/C++ toolchain '
                        '(apt-get install build-essential)')
    if not (Path(sysconfig.get_paths()['include']) / 'Python.h').is_file():
        pytest.skip('no Python.h for this interpreter: the tf2_msgs build needs the Python '
                    'development headers')
    prefix = _cache_dir('tf2_msgs')
    done = _locked_run(prefix.with_suffix('.lock'),
                       [str(TF2_MSGS_BUILD), sys.executable, str(prefix)], 600)
    assert done.returncode == 0, f'tf2_msgs build failed:\n{done.stderr[-3000:]}'
    env = dict(os.environ)
    for line in done.stdout.splitlines():      # export NAME="value${NAME:+:$NAME}"
        name, value = line.removeprefix('export ').split('=', 1)
        value = value.strip('"').split('${')[0].rstrip(':')
        old = env.get(name)
        env[name] = f'{value}{os.pathsep}{old}' if old else value
    return env


@pytest.fixture(scope='session')
def ros2_cli() -> Path:
    """The folder holding the real Jazzy `ros2` CLI (installed once per venv from the tool).

    Use as `PYTHONPATH=<folder> <folder>/bin/ros2`. Skips with the reason when the tool is
    missing.
    """
    if not ROS2CLI_INSTALL.is_file():
        pytest.skip(f'ros2 CLI install tool not found at {ROS2CLI_INSTALL}')
    target = _cache_dir('ros2cli')
    done = _locked_run(target.with_suffix('.lock'),
                       [str(ROS2CLI_INSTALL), sys.executable, str(target)], 300)
    assert done.returncode == 0, f'ros2 CLI install failed:\n{done.stderr[-3000:]}'
    assert (target / 'bin' / 'ros2').is_file()
    return target


@pytest.fixture(scope='session')
def colcon_install(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The package built once with the venv's colcon; returns install/kneeseat_ros.

    `pip install --prefix` would put the scripts in bin/, which `ros2 run` does not search.
    """
    colcon = Path(sys.prefix) / 'bin' / 'colcon'
    if not colcon.exists():
        pytest.fail(f'{colcon} missing: run ./scripts/setup (requirements/dev.txt has '
                    'colcon-common-extensions)')
    ws = tmp_path_factory.mktemp('ws')
    src = ws / 'src' / 'kneeseat_ros'
    src.mkdir(parents=True)
    ignore = shutil.ignore_patterns('__pycache__', '*.pyc', '*.egg-info')
    for name in ('package.xml', 'setup.py', 'setup.cfg', 'resource', 'kneeseat_core',
                 'kneeseat_ros', 'config'):
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, src / name, ignore=ignore)
        else:
            shutil.copy2(REPO / name, src / name)
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE='1')
    done = subprocess.run([str(colcon), 'build', '--base-paths', 'src'], cwd=ws, env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f'colcon build failed:\n{done.stdout}\n{done.stderr}'
    return ws / 'install' / 'kneeseat_ros'


def install_env(prefix: Path, base: dict[str, str] | None = None) -> dict[str, str]:
    """What `source install/setup.bash` would set, on top of the venv's ROS wheels."""
    py = f'python{sys.version_info.major}.{sys.version_info.minor}'
    site = prefix / 'lib' / py / 'site-packages'
    env = dict(os.environ if base is None else base)
    env['PYTHONPATH'] = os.pathsep.join([str(site), *filter(None, [env.get('PYTHONPATH')])])
    ament = [p for p in env.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    env['AMENT_PREFIX_PATH'] = os.pathsep.join(
        [str(prefix), *[p for p in ament if p != str(prefix)],
         *([] if sys.prefix in ament else [sys.prefix])])
    return env


def assert_same_poses(ours: Path, theirs: Path) -> None:
    """The two bags hold the same messages (topic, times, header, position: exact) with
    orientations equal to within two units in the last place: numpy's vectorised sin and
    cos differ by one between CPUs with AVX-512 and without."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)

    def poses(bag: Path) -> list[tuple[str, int, Any]]:
        with Reader(bag) as reader:
            return [(c.topic, t, store.deserialize_cdr(raw, c.msgtype))
                    for c, t, raw in reader.messages()]

    a, b = poses(ours), poses(theirs)
    assert len(a) == len(b)
    for (topic, t, msg), (topic2, t2, msg2) in zip(a, b):
        assert (topic, t) == (topic2, t2)
        assert msg.header == msg2.header and msg.pose.position == msg2.pose.position
        q, q2 = msg.pose.orientation, msg2.pose.orientation
        assert np.allclose([q.x, q.y, q.z, q.w], [q2.x, q2.y, q2.z, q2.w], rtol=0, atol=4.5e-16)
