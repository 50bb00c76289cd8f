"""`kneeseat kinematics`: the secondary motions of a table, on tables with known answers.

The synthetic tables are built from the definitions' own ingredients (Grood and Suntay
axes: e1 the femoral flexion axis, e3 the moving bone's long axis, e2 = e3 x e1): a tibia
whose landmark moves by chosen amounts along e2, e3 and e1 while it flexes and turns
internally, and a patella that flexes, spins, tilts and shifts by chosen amounts.
"""
from __future__ import annotations

import math
from pathlib import Path

from matplotlib.colors import to_rgb
import numpy as np
import pytest

from conftest import pixels_near, synthetic_table
from kneeseat_core.cli import main
from kneeseat_core.errors import ConfigError
from kneeseat_core.geometry import quat_from_matrix, rotation_about
from kneeseat_core.report import (kinematics_markdown, knee_kinematics, Landmarks, landmarks,
                                  plot_kinematics, read_reference)
from kneeseat_core.table import PoseTable, write_table

X, Y, Z = np.eye(3)
KNEE_DEG = np.arange(0.0, 91.0, 15.0)          # knee flexion; the grid holds its negative
P = np.array([0.004, -0.022, 0.002])           # plateau centre, tibia frame (m)
HALF = 0.02                                    # medial/lateral centres 20 mm either side
Q = np.array([0.05, 0.006, 0.004])             # patellar landmark, patella frame (m)
# chosen motions per degree of knee flexion
AP, PD, ML, IE = -0.04e-3, 0.01e-3, -0.02e-3, 0.2        # m, m, m, deg
PF, SPIN, TILT, SHIFT = 0.65, 0.03, 0.05, 0.03e-3        # deg, deg, deg, m


def rz(deg: float) -> np.ndarray:
    return rotation_about(Z, math.radians(deg))


def tibia_pose(knee: float) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of a tibia at `knee` deg of flexion with the chosen motions."""
    rot = rz(-knee) @ rotation_about(Y, math.radians(IE * knee))
    e1, e2, e3 = Z, rz(-knee) @ X, rz(-knee) @ Y
    want = (P @ X + AP * knee) * e2 + (P @ Y + PD * knee) * e3 + (P @ Z + ML * knee) * e1
    return rot, want - rot @ P


def patella_pose(knee: float) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of a patella: flexion PF, spin -SPIN (distal pole medial), tilt -TILT."""
    rot = (rz(-PF * knee) @ rotation_about(X, math.radians(-SPIN * knee))
           @ rotation_about(Y, math.radians(-TILT * knee)))
    where = rz(-PF * knee) @ Q + np.array([0.0, 0.0, SHIFT * knee])
    return rot, where - rot @ Q


def chosen_motions(f: np.ndarray, v: np.ndarray,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """conftest's pose model of these tables: `tibia_pose` and `patella_pose` at each
    cell's knee flexion (minus the grid's flexion), the same at every varus."""
    rot, pos = np.empty((2, *f.shape, 3, 3)), np.empty((2, *f.shape, 3))
    for (i, j), flexion in np.ndenumerate(f):
        for b, pose in enumerate((tibia_pose, patella_pose)):
            rot[b, i, j], pos[b, i, j] = pose(-math.degrees(flexion))
    return rot, pos


def synthetic(nonconverged_at: float | None = None,
              knee_deg: np.ndarray = KNEE_DEG) -> PoseTable:
    """The chosen motions on the grid -knee_deg x varus -5, 0, 5 deg; the tibia's cell at
    knee flexion `nonconverged_at`, varus 0, not converged."""
    flexion = np.radians(-knee_deg[::-1])
    cells = [] if nonconverged_at is None else \
        [(0, int(np.argmin(np.abs(flexion + math.radians(nonconverged_at)))), 1)]
    return synthetic_table(flexion_rad=flexion, varus_rad=np.radians([-5.0, 0.0, 5.0]),
                           poses=chosen_motions, nonconverged=cells, iterations=1,
                           meta={'name': 'synthetic'})


MARKS = Landmarks(P, P - HALF * Z, P + HALF * Z, Q)


def test_known_motions_come_back() -> None:
    kin = knee_kinematics(synthetic(), MARKS)
    np.testing.assert_allclose(kin.knee_flexion_deg, KNEE_DEG)
    v = kin.values
    np.testing.assert_allclose(v['tibia_ap'], AP * KNEE_DEG * 1e3, atol=1e-9)
    np.testing.assert_allclose(v['tibia_pd'], PD * KNEE_DEG * 1e3, atol=1e-9)
    np.testing.assert_allclose(v['tibia_ml'], ML * KNEE_DEG * 1e3, atol=1e-9)
    np.testing.assert_allclose(v['tibia_ie'], IE * KNEE_DEG, atol=1e-9)
    # internal rotation takes the medial plateau back and the lateral one forward
    turn = HALF * np.sin(np.radians(IE * KNEE_DEG)) * 1e3
    np.testing.assert_allclose(v['tibia_ap_medial'], AP * KNEE_DEG * 1e3 - turn, atol=1e-9)
    np.testing.assert_allclose(v['tibia_ap_lateral'], AP * KNEE_DEG * 1e3 + turn, atol=1e-9)
    np.testing.assert_allclose(v['patella_flexion'], PF * KNEE_DEG, atol=1e-9)
    np.testing.assert_allclose(v['patella_spin'], SPIN * KNEE_DEG, atol=1e-9)
    np.testing.assert_allclose(v['patella_tilt'], TILT * KNEE_DEG, atol=1e-9)
    np.testing.assert_allclose(v['patella_ml'], SHIFT * KNEE_DEG * 1e3, atol=1e-9)
    assert kin.varus_deg == 0.0 and not any(f.any() for f in kin.nonconverged.values())


def test_left_knee_flips_the_side_dependent_signs() -> None:
    right = knee_kinematics(synthetic(), MARKS).values
    left = knee_kinematics(synthetic(), MARKS, side='left').values
    for q in ('tibia_ml', 'tibia_ie', 'patella_ml', 'patella_tilt', 'patella_spin'):
        np.testing.assert_allclose(left[q], -right[q], atol=1e-12)
    for q in ('tibia_ap', 'tibia_pd', 'patella_flexion'):
        np.testing.assert_allclose(left[q], right[q], atol=1e-12)


def test_pure_flexion_about_the_femoral_axis_is_no_translation() -> None:
    table = synthetic()
    rot = rz(-90.0)
    pos = np.array(table.position_m)
    pos[0, 0, 1] = np.zeros(3)                    # grid row 0 is -90 deg: a pure hinge
    quat = np.array(table.orientation_xyzw)
    quat[0, 0, 1] = quat_from_matrix(rot)
    hinge = PoseTable(table.flexion_rad, table.varus_rad, pos, quat, table.converged,
                      table.iterations, table.metadata)
    kin = knee_kinematics(hinge, Landmarks(P), angles_deg=[0.0, 90.0], patella=None)
    first = tibia_pose(0.0)
    # at 0 deg the synthetic tibia sits where its motions start; at 90 deg the hinge has
    # moved the landmark by R P - (R0 P + t0) only through the rotation: no G&S translation
    assert np.allclose(first[1], 0.0) and np.allclose(first[0], np.eye(3))
    np.testing.assert_allclose([kin.values[q][1] for q in ('tibia_ap', 'tibia_pd',
                                                           'tibia_ml')], 0.0, atol=1e-12)


def test_grid_nodes_are_looked_up_on_the_node() -> None:
    """On a 1-degree grid, -48 deg in radians does not come back bit for bit from degrees;
    the node's row must still be the node's own cell, not a blend that carries a
    non-converged neighbour's flag."""
    fine = np.arange(0.0, 91.0)
    node = -math.radians(48.0)
    assert math.radians(math.degrees(node)) != node       # the case this guards
    table = synthetic(knee_deg=fine)
    converged = np.array(table.converged)
    for neighbour in (47.0, 49.0):
        converged[0, int(np.argmin(np.abs(np.asarray(table.flexion_rad)
                                          + math.radians(neighbour)))), 1] = False
    table = PoseTable(table.flexion_rad, table.varus_rad, table.position_m,
                      table.orientation_xyzw, converged, table.iterations, table.metadata)
    flags = knee_kinematics(table, MARKS).nonconverged['tibia']
    assert flags.tolist() == [k in (47, 49) for k in range(91)]


def test_angles_between_nodes_are_interpolated_and_flags_shown() -> None:
    kin = knee_kinematics(synthetic(nonconverged_at=45.0), MARKS,
                          angles_deg=[0.0, 7.5, 45.0, 90.0])
    # the table blends poses (positions linearly, orientations by quaternion), so a landmark
    # between nodes is near, not exactly on, the chosen line
    assert kin.values['tibia_ap'][1] == pytest.approx(AP * 7.5 * 1e3, abs=0.03)
    assert kin.values['tibia_ie'][1] == pytest.approx(IE * 7.5, abs=1e-3)
    assert kin.nonconverged['tibia'].tolist() == [False, False, True, False]
    assert not kin.nonconverged['patella'].any()
    text = kinematics_markdown(kin)
    rows = [ln for ln in text.splitlines() if ln.startswith('| 45 ')]
    assert len(rows) == 1 and rows[0].count('*') == 6      # the six tibial columns
    assert '* from a non-converged cell' in text
    with pytest.raises(ConfigError, match=r'\[100\.0\] deg are outside the table \(0 to 90'):
        knee_kinematics(synthetic(), MARKS, angles_deg=[0.0, 100.0])


def test_landmarks_of_two_sheets() -> None:
    import trimesh
    sheets = [trimesh.creation.box((0.02, 0.002, 0.02)) for _ in range(2)]
    sheets[0].apply_translation((0.0, -0.02, -0.02))          # medial (right knee: -Z)
    sheets[1].apply_translation((0.001, -0.02, 0.022))
    marks = landmarks(trimesh.util.concatenate(sheets), None, Z)
    np.testing.assert_allclose(marks.tibia_medial, [0.0, -0.02, -0.02], atol=1e-12)
    np.testing.assert_allclose(marks.tibia_lateral, [0.001, -0.02, 0.022], atol=1e-12)
    np.testing.assert_allclose(marks.tibia_centre, [0.0005, -0.02, 0.001], atol=1e-12)
    assert marks.patella_centre is None


def test_cli_writes_csv_markdown_and_png(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    table_path = tmp_path / 'synthetic.npz'
    write_table(table_path, synthetic())
    reference = tmp_path / 'published.csv'
    reference.write_text('# a comment line\nsource,quantity,knee_flexion_deg,value,citation\n'
                         'A 2000,tibia_ie,90,15,J X 1:1\nB 2005,patella_flexion,60,40,\n')
    rows = read_reference(reference)
    assert [(r['source'], r['value']) for r in rows] == [('A 2000', 15.0), ('B 2005', 40.0)]
    code = main(['kinematics', str(table_path), '--out-dir', str(tmp_path / 'k'),
                 '--tibia-point', f'{P[0]},{P[1]},{P[2]}', '--patella-point',
                 f'{Q[0]},{Q[1]},{Q[2]}', '--reference', str(reference)])
    assert code == 0
    out = capsys.readouterr().out
    assert '| 90 | -3.6 | 0.9 | -1.8 | 18.0 |' in out
    lines = (tmp_path / 'k' / 'kinematics.csv').read_text().splitlines()
    assert lines[0].startswith('knee_flexion_deg,tibia_ap,tibia_pd,tibia_ml,tibia_ie,')
    assert len(lines) == 1 + len(KNEE_DEG)
    assert (tmp_path / 'k' / 'kinematics.png').stat().st_size > 10_000
    reference.write_text('source,quantity,knee_flexion_deg,value\nA,tibia_spin,90,1\n')
    assert main(['kinematics', str(table_path), '--out-dir', str(tmp_path / 'k'),
                 '--reference', str(reference), '--tibia-point', '0,0,0',
                 '--patella-point', '0,0,0']) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown quantity 'tibia_spin'" in err[0]


def test_plot_draws_other_tables(tmp_path: Path) -> None:
    """Another table is a dashed orange line, drawn through its converged cells only."""
    kin = knee_kinematics(synthetic(), MARKS)
    gappy = knee_kinematics(synthetic(nonconverged_at=45.0), MARKS)
    orange = to_rgb('tab:orange')                    # the first other table's colour only
    alone = pixels_near(plot_kinematics(kin, tmp_path / 'alone.png', title='t'), orange)
    full = pixels_near(plot_kinematics(kin, tmp_path / 'full.png', title='t',
                                       others={'other': kin}), orange)
    gap = pixels_near(plot_kinematics(kin, tmp_path / 'gap.png', title='t',
                                      others={'other': gappy}), orange)
    assert alone == 0 < gap < 0.9 * full         # the tibial lines break at 45 deg


def test_kinematics_refuses_an_output_directory_under_a_file_before_the_work(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    blocker = tmp_path / 'a_file'
    blocker.write_text('not a directory')
    code = main(['kinematics', str(tmp_path / 'no_table.npz'), '--out-dir',
                 str(blocker / 'k')])
    err = capsys.readouterr().err
    assert code == 2 and len(err.splitlines()) == 1 and 'Traceback' not in err, err
    assert f'--out-dir {blocker / "k"}: cannot write the kinematics there ({blocker} is not ' \
        'a directory)' in err, err
    assert [p.name for p in tmp_path.iterdir()] == ['a_file']
