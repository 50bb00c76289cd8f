"""The default knee's sweep and table: convergence, continuity, screw-home, mid-cells, rest.

How cells are compared (docs/tables.md gives the reasons):
- position: the distance between the body frame origins of two cells (m). The default
  knee's tibia and patella frames are the femur frame at neutral, so the origin sits at
  the knee centre and a commanded change of attitude (a rotation about an axis through
  the origin) does not move it; what moves it is what settling found.
- rotation: the settle may only spin a body about its push, so R = A @ S with A the
  commanded attitude of the cell and S a rotation about the body's neutral push. The
  *spin* is S's signed angle about that push; adjacent cells are compared by the change of
  spin (the angle of R_a^T R_b minus the commanded 1 degree step is bounded by it).

The full-grid tests (`slow`) build the patent grid once per module with 2 workers
(about 1-2 minutes on the shared 2-core machine); the others use a coarse grid.
"""
from __future__ import annotations

from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
import json
import math
from pathlib import Path

import numpy as np
import pytest

from kneeseat_core.knee import materialise_default_knee
from kneeseat_core.cli import main
from kneeseat_core.meshes import load_mesh, RigidBody
from kneeseat_core.geometry import matrix_from_quat, pose_from, rotation_about, rotation_angle
from kneeseat_core.knee import BodySpec, KneeConfig, load_config
from kneeseat_core.settle import settle
from kneeseat_core.sweep import warm_start
from kneeseat_core.referee import body_load, Referee, verify_table
from kneeseat_core.table import PoseTable, read_table, write_table
from kneeseat_core.typed import Floats

MAX_STEP_MM = 1.0           # Show list: adjacent cells differ by <= 1 mm ...
MAX_STEP_DEG = 2.0          # ... and <= 2 degrees
MID_POSITION_MM = 0.5       # interpolation vs direct settle at mid-cells
MID_ROTATION_DEG = 0.5
N_MIDPOINTS = 10


@dataclass(frozen=True, slots=True)
class Knee:
    """A built default-knee table with the config it came from."""

    config: KneeConfig
    table: PoseTable
    mesh_dir: Path


def build_default(out_dir: Path, monkeypatch: pytest.MonkeyPatch, *grid: str,
                  workers: int = 2) -> Knee:
    """`kneeseat build` of the embedded default knee (meshes cached under `out_dir`)."""
    monkeypatch.setenv('XDG_CACHE_HOME', str(out_dir / 'cache'))
    out = out_dir / 'default_knee.npz'
    assert main(['build', '--out', str(out), '--workers', str(workers), '--quiet',
                 *grid]) == 0
    config_path = materialise_default_knee()          # same cache: the files just used
    overrides = None
    if grid:
        spec = dict(zip(grid[::2], grid[1::2]))
        overrides = {'grid': {
            'flexion_deg': [float(v) for v in spec['--flexion-grid'].split(',')],
            'varus_deg': [float(v) for v in spec['--varus-grid'].split(',')]}}
    config = load_config(config_path, config_path.parent, overrides)
    meshes = {config.reference.name: config.reference.mesh}
    meshes.update({b.name: b.mesh for b in config.bodies})
    return Knee(config, read_table(out, meshes=meshes), config_path.parent)


def attitudes(config: KneeConfig, spec: BodySpec, table: PoseTable) -> Floats:
    """(F, V, 3, 3) commanded attitude A of `spec` at every cell."""
    return np.array([[config.attitude(spec, f, v) for v in table.varus_rad]
                     for f in table.flexion_rad])


def spin_deg(config: KneeConfig, table: PoseTable, body: int) -> tuple[Floats, Floats]:
    """Signed spin (deg) about the neutral push at every cell, and the largest residual
    rotation (deg) about any other axis (zero when the table obeys the settle's rule)."""
    spec = config.bodies[body]
    residual = (np.swapaxes(attitudes(config, spec, table), -1, -2)
                @ matrix_from_quat(table.orientation_xyzw[body]))          # S = A^T R
    push = np.asarray(spec.push)
    vee = 0.5 * np.stack([residual[..., 2, 1] - residual[..., 1, 2],
                          residual[..., 0, 2] - residual[..., 2, 0],
                          residual[..., 1, 0] - residual[..., 0, 1]], axis=-1)
    cos = 0.5 * (np.trace(residual, axis1=-2, axis2=-1) - 1.0)
    spin = np.degrees(np.arctan2(vee @ push, cos))
    angle = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return spin, np.abs(angle - np.abs(spin))


def steps(config: KneeConfig, table: PoseTable, body: int, axis: int) -> tuple[Floats, Floats]:
    """Position change (mm) and spin change (deg) between neighbours along grid `axis`
    (0 flexion, 1 varus)."""
    spin, _ = spin_deg(config, table, body)
    moved = np.linalg.norm(np.diff(table.position_m[body], axis=axis), axis=-1) * 1e3
    return moved, np.abs(np.diff(spin, axis=axis))


def describe_steps(name: str, moved: Floats, turned: Floats, table: PoseTable,
                   axis: int) -> str:
    i, j = np.unravel_index(np.argmax(moved), moved.shape)
    k, m = np.unravel_index(np.argmax(turned), turned.shape)
    deg = (np.degrees(table.flexion_rad), np.degrees(table.varus_rad))
    return (f'{name} {("flexion", "varus")[axis]}-adjacent: position max {moved.max():.3f} mm '
            f'(at flexion {deg[0][i]:g}, varus {deg[1][j]:g}), {int((moved > MAX_STEP_MM).sum())}'
            f' of {moved.size} pairs > {MAX_STEP_MM} mm; spin max {turned.max():.3f} deg (at '
            f'flexion {deg[0][k]:g}, varus {deg[1][m]:g}), {int((turned > MAX_STEP_DEG).sum())}'
            f' pairs > {MAX_STEP_DEG} deg')


# ---- coarse grid (fast) ------------------------------------------------------------------
def test_coarse_build_converges_and_only_spins_about_the_push(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    knee = build_default(tmp_path, monkeypatch, '--flexion-grid', '0,-90,15',
                         '--varus-grid', '-10,10,5', workers=1)
    table = knee.table
    assert table.position_m.shape == (2, 7, 5, 3)
    assert table.converged.all()
    for b, name in enumerate(table.bodies):
        spin, off_axis = spin_deg(knee.config, table, b)
        assert off_axis.max() < 1e-6, f'{name} turned about an axis other than its push'
    # the patella ignores varus: every varus column holds the same poses
    patella = table.bodies.index('patella')
    assert np.array_equal(table.position_m[patella], np.broadcast_to(
        table.position_m[patella, :, :1], table.position_m[patella].shape))
    # screw-home: the tibia's spin about its long axis changes with flexion
    tibia_spin, _ = spin_deg(knee.config, table, table.bodies.index('tibia'))
    column = tibia_spin[:, len(table.varus_rad) // 2]
    print(f'coarse tibia spin at varus 0 (flexion -90..0 by 15): {np.round(column, 2)}')
    assert np.ptp(column) > 2.0


# ---- full patent grid (slow) -------------------------------------------------------------
@pytest.fixture(scope='module')
def full(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Knee]:
    """The default knee at the patent grid, built once for this module (2 workers)."""
    with pytest.MonkeyPatch.context() as monkeypatch:
        yield build_default(tmp_path_factory.mktemp('default_full'), monkeypatch)


@pytest.mark.slow
def test_full_grid_all_cells_converge(full: Knee) -> None:
    table = full.table
    assert table.position_m.shape == (2, 91, 21, 3)
    summary = table.metadata['summary']
    print(f'default knee full grid: {summary}')
    assert table.converged.all()


def pairs_over_bound(knee: Knee, b: int, axis: int) -> list[tuple[tuple[int, int], ...]]:
    """Adjacent cells of body `b` along `axis` whose step exceeds 1 mm or 2 degrees."""
    moved, turned = steps(knee.config, knee.table, b, axis=axis)
    print(describe_steps(knee.table.bodies[b], moved, turned, knee.table, axis=axis))
    di, dj = (1, 0) if axis == 0 else (0, 1)
    return [((int(i), int(j)), (int(i) + di, int(j) + dj))
            for i, j in np.argwhere((moved > MAX_STEP_MM) | (turned > MAX_STEP_DEG))]


def assert_jumps_are_recorded_branch_changes(knee: Knee, axis: int) -> None:
    """Neighbours differ by at most 1 mm / 2 deg, except at a branch change: both cells
    verified at rest (by the independent referee, here on up to 8 of them) and recorded in
    the table's metadata; and such pairs stay rare. Where the tibia bears on one condyle its
    spin is only weakly held, and neighbouring ribs settle up to about 2.5 deg apart (4 % of
    the flexion pairs on the current knee; docs/tables.md): the guard is 6 %."""
    table = knee.table
    deg_f, deg_v = np.degrees(table.flexion_rad), np.degrees(table.varus_rad)
    recorded = {(c['body'], tuple(map(tuple, c['between'])))
                for c in table.metadata['continuity']['branch_changes']}
    n_pairs = (len(deg_f) - (axis == 0)) * (len(deg_v) - (axis == 1))
    for b, name in enumerate(table.bodies):
        over = pairs_over_bound(knee, b, axis)
        assert len(over) <= 0.06 * n_pairs, f'{name}: {len(over)} of {n_pairs} pairs jump'
        for a, c in over:
            key = (name, ((round(deg_f[a[0]], 6), round(deg_v[a[1]], 6)),
                          (round(deg_f[c[0]], 6), round(deg_v[c[1]], 6))))
            assert key in recorded, f'{key} jumps but is not recorded as a branch change'
        cells = sorted({cell for pair in over for cell in pair})[:8]
        spec = knee.config.bodies[b]
        for i, j in cells:
            params = knee.config.params(spec, table.flexion_rad[i], table.varus_rad[j])
            referee = Referee([load_mesh(knee.config.reference.mesh)], [load_mesh(spec.mesh)],
                              np.asarray(params.push), params.resolution_m)
            pose = pose_from(matrix_from_quat(table.orientation_xyzw[b, i, j]),
                             table.position_m[b, i, j])
            assert referee.judge(pose).gain_m <= params.resolution_m


@pytest.mark.slow
def test_full_grid_flexion_neighbours_are_close(full: Knee) -> None:
    assert_jumps_are_recorded_branch_changes(full, axis=0)


@pytest.mark.slow
def test_full_grid_varus_neighbours_are_close(full: Knee) -> None:
    assert_jumps_are_recorded_branch_changes(full, axis=1)


@pytest.mark.slow
def test_full_grid_sampled_cells_are_at_rest(full: Knee, tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    """`kneeseat verify --sample 60` on the default knee: nothing gains a resolution."""
    path = tmp_path / 'default_knee.npz'
    write_table(path, full.table)
    code = main(['verify', str(path), '--sample', '60', '--workers', '2', '--quiet', '--json'])
    report = json.loads(capsys.readouterr().out)
    gains = [c['gain_m'] for c in report['cells'] if c['converged']]
    print(f'default knee verify --sample 60: largest gain {max(gains) * 1e3:.3f} mm')
    assert code == 0 and report['not_at_rest'] == 0 and len(gains) == len(report['cells'])


@pytest.mark.slow
def test_full_grid_screw_home(full: Knee, tmp_path: Path) -> None:
    table = full.table
    spin, off_axis = spin_deg(full.config, table, table.bodies.index('tibia'))
    assert off_axis.max() < 1e-6
    ranges = np.ptp(spin, axis=0)                 # per varus column, over flexion
    centre = len(table.varus_rad) // 2
    print(f'tibia spin at varus 0, flexion -90..0 by 10: {np.round(spin[::10, centre], 2)}; '
          f'range over flexion per varus column (deg, varus -10..10): {np.round(ranges, 2)}')
    # screw-home: at neutral varus both condyles bear and the tibia follows the lateral
    # one (5.7 deg over the range); the ribs carry that spin out to every varus value
    # (sweep.py), where the collaterals, stretched by the varus, hold part of it back
    # (2.0 deg at varus 10)
    assert ranges[centre] > 4.0 and ranges.min() > 1.5
    # internal rotation grows with flexion, monotonic to within 0.2 deg (how closely the
    # contacts hold the spin at the patent's resolution) wherever the rests hold it that
    # closely: where the spin steps back by more (a few flexion values at most), the
    # referee must find both rests of the step determined no better than the step, their
    # extent (how far each can spin while the objective stays within one resolution of
    # the best) at least as wide
    steps = np.diff(spin[:, centre])
    back = np.flatnonzero(steps > 0.2)
    assert len(back) <= 3, f'the spin at varus 0 steps back at {len(back)} flexion values'
    if len(back) == 0:
        return
    path = tmp_path / 'default_knee.npz'
    write_table(path, table)
    tibia = table.bodies.index('tibia')
    cells = sorted({(tibia, int(i) + k, centre) for i in back for k in (0, 1)})
    with ProcessPoolExecutor(2) as pool:
        verdicts = list(verify_table(path, cells, pool))
    flexion_deg = np.degrees(table.flexion_rad)
    for i in back:
        for k in (0, 1):
            verdict = min(verdicts, key=lambda v: abs(v.flexion_deg - flexion_deg[i + k]))
            assert verdict.converged and verdict.extent_deg is not None
            assert verdict.extent_deg >= steps[i], \
                (f'the spin steps back {steps[i]:.3f} deg at flexion {flexion_deg[i]:g}, '
                 f'where the rest at {verdict.flexion_deg:g} holds it to '
                 f'{verdict.extent_deg:.3f} deg')


@dataclass(frozen=True, slots=True)
class MidCell:
    """A direct settle at a mid-cell attitude against the table's interpolation there."""

    body: str
    flexion_deg: float
    varus_deg: float
    position_mm: float       # distance between the two positions
    rotation_deg: float      # angle between the two orientations
    lookup_gain_mm: float    # what the referee still gains from the interpolated pose


@pytest.fixture(scope='module')
def midcells(full: Knee) -> list[MidCell]:
    """N_MIDPOINTS seeded mid-cells, each settled directly (every body, with the ligaments
    the table was built with, each body's fibres placed by the bodies settled before it
    there) and interpolated; the referee judges the same objective with its own energy."""
    config, table = full.config, full.table
    assert config.ligaments is not None
    rng = np.random.default_rng(20260901)
    flexion, varus = table.flexion_rad, table.varus_rad
    fixed = RigidBody.from_mesh(load_mesh(config.reference.mesh))
    bodies = [RigidBody.from_mesh(load_mesh(spec.mesh)) for spec in config.bodies]
    out = []
    for _ in range(N_MIDPOINTS):
        i, j = int(rng.integers(0, len(flexion) - 1)), int(rng.integers(0, len(varus) - 1))
        f, v = 0.5 * (flexion[i] + flexion[i + 1]), 0.5 * (varus[j] + varus[j + 1])
        lookup = table.interpolate(f, v)
        placed = {config.reference.name: np.eye(4)}
        for b, spec in enumerate(config.bodies):
            # warm start from the nearest node (all four are equally near: take the
            # first corner), turned to the mid-cell attitude as the sweep does
            node = pose_from(matrix_from_quat(table.orientation_xyzw[b, i, j]),
                             table.position_m[b, i, j])
            params = config.params(spec, f, v)
            start = warm_start(node, config.attitude(spec, flexion[i], varus[j]),
                               config.attitude(spec, f, v), np.asarray(params.push),
                               params.step_m)
            result = settle(fixed, bodies[b], start, params,
                            tissue=config.ligaments.tissue(spec.name, placed))
            assert result.converged, result.reason
            referee = Referee([fixed.mesh], [bodies[b].mesh], np.asarray(params.push),
                              params.resolution_m,
                              load=body_load(config, config.ligaments, params, spec, placed))
            placed[spec.name] = result.pose
            interpolated = pose_from(matrix_from_quat(lookup.orientation_xyzw[b]),
                                     lookup.position_m[b])
            interpolated[:3, 3] += referee.travel(interpolated) * np.asarray(params.push)
            out.append(MidCell(spec.name, math.degrees(f), math.degrees(v),
                               float(np.linalg.norm(result.pose[:3, 3]
                                                    - lookup.position_m[b])) * 1e3,
                               math.degrees(rotation_angle(result.pose[:3, :3],
                                                           interpolated[:3, :3])),
                               referee.judge(interpolated).gain_m * 1e3))
    for m in out:
        print(f'mid-cell {m.body:7s} flexion {m.flexion_deg:6.1f} varus {m.varus_deg:5.1f}: '
              f'{m.position_mm:.3f} mm, {m.rotation_deg:.3f} deg from a direct settle; the '
              f'referee gains {m.lookup_gain_mm:.3f} mm from the interpolated pose')
    return out


@pytest.mark.slow
def test_every_mid_cell_matches_a_direct_settle(midcells: list[MidCell]) -> None:
    """Interpolation agrees with a direct settle within 0.5 mm / 0.5 deg, or - where the
    rest is only weakly determined (a flat valley, a branch change) - the interpolated
    pose, brought to contact, is itself at rest for the independent referee."""
    far = [m for m in midcells
           if m.position_mm > MID_POSITION_MM or m.rotation_deg > MID_ROTATION_DEG]
    print(f'mid-cells: worst {max(m.position_mm for m in midcells):.3f} mm, '
          f'{max(m.rotation_deg for m in midcells):.3f} deg; {len(far)} of {len(midcells)} '
          'farther from a direct settle, the referee gains from them: '
          + ', '.join(f'{m.lookup_gain_mm:.3f} mm' for m in far))
    assert len(far) <= 0.25 * len(midcells)
    assert all(m.lookup_gain_mm <= 0.1 for m in far)


def test_an_attitude_asked_again_is_the_same_turn_and_the_callers_own() -> None:
    """A config keeps the turns it computed (a sweep asks each cell's several times): asked
    again, an attitude is the same turn about the knee's axes, and a caller that changes
    the array it was given changes nothing the config keeps."""
    config = load_config(materialise_default_knee())
    tibia, patella = config.bodies
    f, v = config.flexion_rad[3], config.varus_rad[2]
    turn = (rotation_about(config.axes.flexion, patella.flexion_fraction * f)
            @ rotation_about(config.axes.varus, patella.varus_fraction * v))
    first = config.attitude(patella, f, v)
    np.testing.assert_array_equal(first, turn)
    first[:] = 0.0
    np.testing.assert_array_equal(config.attitude(patella, f, v), turn)
    assert not np.array_equal(config.attitude(tibia, f, v), turn)
