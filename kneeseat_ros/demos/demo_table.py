"""The demo's table and bag: build the chosen knee's table on a coarse grid, or reuse it.

`prepare_table` builds `DIR/<config name>_<step>deg.npz` for the default (embedded) or
the natural knee, or reuses the file there when `read_table` accepts it, it was built from
these meshes and it has the requested grid. `demo_bag` finds the shipped gait angle bag,
or regenerates it byte for byte where the repository is not there.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from kneeseat_core.errors import ConfigError, KneeseatError, MeshError, TableError
from kneeseat_core.geometry import TOL
from kneeseat_core.knee import KneeConfig, load_config
from kneeseat_core.knee import materialise_default_knee
from kneeseat_core.sweep import build_table, executor_for
from kneeseat_core.table import PoseTable, read_table
from kneeseat_ros.errors import DataMissing

__all__ = ['KNEES', 'NATURAL_CONFIG', 'SHIPPED_BAG', 'DEFAULT_STEP_DEG', 'prepare_table',
           'demo_bag']

DEFAULT_STEP_DEG = 2.0                 # 46 x 11 grid: about a quarter of the full build
FLEXION_RANGE_DEG = (0.0, -90.0)       # the patent's knee grid
VARUS_RANGE_DEG = (-10.0, 10.0)
SHIPPED_BAG = Path(__file__).resolve().parents[2] / 'data' / 'angle_bags' / 'gait_demo'
NATURAL_CONFIG = Path(__file__).resolve().parents[2] / 'config' / 'natural_knee.yaml'
KNEES = ('default', 'natural')


def _demo_config(out_dir: Path, step_deg: float, knee: str = 'default',
                 mesh_dir: Path | None = None) -> KneeConfig:
    grid = {'flexion_deg': [*FLEXION_RANGE_DEG, step_deg],
            'varus_deg': [*VARUS_RANGE_DEG, step_deg]}
    if knee == 'default':
        config = materialise_default_knee(out_dir / 'default_knee')
        return load_config(config, config.parent, {'grid': grid})
    if knee != 'natural':
        raise ConfigError(f"knee {knee!r} is not a demo knee; use {' or '.join(KNEES)}")
    if not NATURAL_CONFIG.is_file():
        raise DataMissing(f'{NATURAL_CONFIG} not found: --knee natural runs from the '
                          'repository (config/natural_knee.yaml)')
    try:
        return load_config(NATURAL_CONFIG, mesh_dir, {'grid': grid})
    except ConfigError as err:
        raise DataMissing(f'--knee natural needs the natural knee meshes: {err}') from None


def _reusable(path: Path, config: KneeConfig) -> tuple[PoseTable | None, str]:
    """The table at `path` if it can be reused for `config`, else (None, why not)."""
    if not path.exists():
        return None, 'no table yet'
    meshes = {config.reference.name: list(config.reference.meshes),
              **{b.name: list(b.meshes) for b in config.bodies}}
    try:
        table = read_table(path, meshes)
    except (TableError, MeshError) as err:
        return None, f'existing table not usable ({err})'
    if (table.flexion_rad.shape != config.flexion_rad.shape
            or table.varus_rad.shape != config.varus_rad.shape
            or not np.allclose(table.flexion_rad, config.flexion_rad, atol=TOL.grid_same_rad)
            or not np.allclose(table.varus_rad, config.varus_rad, atol=TOL.grid_same_rad)):
        return None, 'existing table has another grid'
    return table, 'reused (read_table verified it and its meshes)'


def prepare_table(out_dir: Path, step_deg: float, workers: int,
                  show_progress: bool = True, knee: str = 'default',
                  mesh_dir: Path | None = None) -> tuple[Path, PoseTable, str]:
    """Build the chosen knee's table on a `step_deg` grid in `out_dir`, or reuse it.

    Args:
        out_dir: demo directory; the default knee's meshes go to `out_dir/default_knee/`.
        step_deg: grid step (deg) for flexion 0..-90 and varus -10..10; must divide 10.
        workers: build processes.
        show_progress: tqdm bar on stderr while building.
        knee: 'default' (embedded) or 'natural' (config/natural_knee.yaml).
        mesh_dir: the natural knee's mesh directory instead of its config's.
    Returns:
        The table path, the verified table, and what happened ('built ...' or 'reused ...').
    Raises:
        DataMissing: the natural knee's meshes are not there.
        ConfigError: the step does not divide the grid ranges.
        KneeseatError: the build failed.
    """
    config = _demo_config(out_dir, step_deg, knee, mesh_dir)
    path = out_dir / f'{config.name}_{step_deg:g}deg.npz'
    table, why = _reusable(path, config)
    if table is not None:
        return path, table, why
    print(f'demo: building the table ({why}): {len(config.flexion_rad)} x '
          f'{len(config.varus_rad)} grid ({step_deg:g} deg steps), {len(config.bodies)} '
          f'bodies, {workers} worker(s)', flush=True)
    executor, close = executor_for(workers, None)
    try:
        build_table(config, path, executor, show_progress=show_progress)
    finally:
        close()
    return path, read_table(path), 'built'


def demo_bag(out_dir: Path, table: PoseTable, shipped: Path = SHIPPED_BAG) -> Path:
    """The shipped gait angle bag, or the same bag regenerated into `out_dir/angle_bags/`.

    Without the repository (an installed package has no `data/`), the bag is written as
    `scripts/make_demo_bag` does (10 s gait cycle, 100 Hz, the same start stamp), with the
    table's axes and reference frame; an earlier regenerated bag is reused.

    Args:
        out_dir: demo directory.
        table: the served table (axes, reference frame).
        shipped: where the shipped bag would be.
    Raises:
        KneeseatError: the bag cannot be written.
    """
    if (shipped / 'metadata.yaml').is_file():
        return shipped
    from kneeseat_ros.bag.make_bag import DEFAULT_START_NS, gait, write_angle_bag
    from kneeseat_ros.bag.replay import load_messages
    bag = out_dir / 'angle_bags' / 'gait_demo'
    try:
        load_messages(bag)
        return bag
    except KneeseatError:
        pass
    n = 0
    while bag.exists():              # an unreadable leftover: never delete, go around it
        n += 1
        bag = out_dir / 'angle_bags' / f'gait_demo_{n}'
    write_angle_bag(bag, gait(10.0, 100.0), table.axes, frame_id=table.reference_frame,
                    start_ns=DEFAULT_START_NS)
    return bag
