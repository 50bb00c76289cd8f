"""Pictures of a pose table: PNGs written, sized, marked, and bad arguments refused."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
import time
from typing import Any, Literal

from matplotlib.colors import to_rgb
from matplotlib.image import imread
import numpy as np
from PIL import Image
import pytest
import trimesh

from conftest import pixels_near, SHARED_DATA, synthetic_table, TKA_AXES
from kneeseat_core.errors import ConfigError, KneeseatError
from kneeseat_core.geometry import KneeAxes, quat_from_matrix
from kneeseat_core.report.plots import (DPI, MARKER_RGB, PLOT_EXTRA_IN, PLOT_PANEL_IN,
                                        PNG_KEY_NONCONVERGED, plot_convergence_map, plot_table)
from kneeseat_core.report.render import render_table, RENDER_EXTRA_IN, RENDER_PANEL_IN
from kneeseat_core.status import Status
from kneeseat_core.table import PoseTable

HASHES = {'femur': 'a1b2c3d4' + '0' * 56, 'tibia': 'deadbeef' + '1' * 56,
          'patella': 'cafef00d' + '2' * 56}


def swing(f: np.ndarray, v: np.ndarray,
          rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """conftest's pose model of these tables: a tibia swinging under the femur, a patella in
    front (see `make_table`), with a seeded jitter of 0.2 mm."""
    knee = KneeAxes.from_vectors(TKA_AXES['flexion'], TKA_AXES['varus'], TKA_AXES['long'])
    tibia_r = knee.orientation(f.ravel(), v.ravel(), np.radians(10.0) * f.ravel() / (np.pi / 2))
    patella_r = knee.orientation(f.ravel() / 3.0, np.zeros(f.size), np.zeros(f.size))
    tibia_p = tibia_r @ np.array([0.0, -0.045, 0.0])                           # (F*V, 3)
    patella_p = patella_r @ np.array([0.040, 0.0, 0.0])
    position = np.stack([tibia_p, patella_p]).reshape(2, *f.shape, 3)
    position = position + rng.normal(0.0, 2e-4, position.shape)
    return np.stack([tibia_r, patella_r]).reshape(2, *f.shape, 3, 3), position


def make_table(*, seed: int = 7, flexion_deg: tuple[float, float, int] = (-90.0, 0.0, 19),
               varus_deg: tuple[float, float, int] = (-10.0, 10.0, 5),
               nonconverged: int | Sequence[tuple[int, int, int]] = 0,
               statuses: dict[tuple[int, int, int], int] | None = None) -> PoseTable:
    """A two-body synthetic table (conftest's builder): a tibia swinging under the femur, a
    patella in front.

    The tibia turns about the flexion axis through the femur's centre with a screw-home
    rotation of 10 deg * flexion / 90 deg; the patella follows at a third of the angle. A
    seeded jitter of 0.2 mm keeps the curves honest. `nonconverged`: that many seeded
    random cells of the tibia, or the cells (body, flexion index, varus index) listed, are
    not converged; `statuses` records settle status codes (conftest's `synthetic_table`).
    """
    n_f, n_v = flexion_deg[2], varus_deg[2]
    if isinstance(nonconverged, int):
        picked = np.random.default_rng(seed).choice(n_f * n_v, size=nonconverged, replace=False)
        nonconverged = [(0, *divmod(int(k), n_v)) for k in picked]
    return synthetic_table(
        seed, [{'name': b, 'mesh': f'{b}.stl', 'mesh_sha256': HASHES[b]}
               for b in ('tibia', 'patella')],
        flexion_deg, varus_deg, poses=swing, nonconverged=nonconverged, statuses=statuses,
        iterations=12, reference={'name': 'femur', 'mesh': 'femur.stl',
                                  'mesh_sha256': HASHES['femur']},
        meta={'name': 'synthetic knee'})


def knee_meshes(subdivisions: int = 3) -> dict[str, trimesh.Trimesh]:
    """Simple bones in their own frames (m): a round femur, a box tibia, a disc patella."""
    femur = trimesh.creation.icosphere(subdivisions=subdivisions, radius=0.025)
    femur.apply_scale([1.0, 1.0, 1.4])
    tibia = trimesh.creation.box(extents=[0.045, 0.06, 0.07])
    patella = trimesh.creation.cylinder(radius=0.015, height=0.01, sections=48)
    patella.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    return {'femur': femur, 'tibia': tibia, 'patella': patella}


def red_pixels(path: Path) -> int:
    """Pixels of the non-converged marker colour (pure red, within antialiasing)."""
    return pixels_near(path, MARKER_RGB)


def png_text(path: Path) -> dict[str, str]:
    """The PNG's tEXt chunks."""
    with Image.open(path) as image:
        return dict(image.text)


def test_plot_writes_png_of_expected_size(tmp_path: Path) -> None:
    table = make_table()
    out = plot_table(table, tmp_path / 'new' / 'dir' / 'plot.png')   # missing dirs created
    assert out == tmp_path / 'new' / 'dir' / 'plot.png'
    image = imread(out)
    bodies = len(table.bodies)
    height = round((bodies * PLOT_PANEL_IN[1] + PLOT_EXTRA_IN) * DPI)
    assert image.shape[:2] == (height, round(4 * PLOT_PANEL_IN[0] * DPI))
    assert image[..., :3].std() > 0.05                               # not a blank canvas
    assert png_text(out)[PNG_KEY_NONCONVERGED] == '0'
    assert red_pixels(out) < 100                     # only the legend's marker is red
    assert not list(out.parent.glob('.*tmp'))                        # no temp file left


def test_plot_marks_nonconverged_cells(tmp_path: Path) -> None:
    table = make_table(nonconverged=40)
    out = plot_table(table, tmp_path / 'plot.png', varus_deg=[-10.0, 0.0, 10.0])
    clean = plot_table(make_table(), tmp_path / 'clean.png', varus_deg=[-10.0, 0.0, 10.0])
    bad = ~table.converged[0][:, [0, 2, 4]]
    assert bad.sum() > 0
    assert png_text(out)[PNG_KEY_NONCONVERGED] == str(int(bad.sum()))
    assert red_pixels(out) > 10 * red_pixels(clean) > 0


def test_plot_picks_nearest_varus_and_accepts_a_title(tmp_path: Path) -> None:
    # j + 1 non-converged tibia cells in varus column j: each column counts differently
    table = make_table(nonconverged=[(0, i, j) for j in range(5) for i in range(j + 1)])
    out = plot_table(table, tmp_path / 'plot.png', varus_deg=[2.0], title='my title')
    assert png_text(out)[PNG_KEY_NONCONVERGED] == '3'            # 2 deg -> column 2, 0 deg
    untitled = plot_table(table, tmp_path / 'untitled.png', varus_deg=[2.0])
    assert imread(out).shape == imread(untitled).shape
    assert (imread(out) != imread(untitled)).any()                # the title is drawn


def test_plot_overwrites_atomically(tmp_path: Path) -> None:
    out = tmp_path / 'plot.png'
    out.write_bytes(b'old')
    plot_table(make_table(varus_deg=(0.0, 0.0, 1)), out)
    assert imread(out).shape[0] > 100
    assert sorted(p.name for p in tmp_path.iterdir()) == ['plot.png']


@pytest.mark.parametrize(('kwargs', 'match'), [
    ({'varus_deg': [25.0]}, r'varus_deg=25 deg outside the table \[-10, 10\] deg'),
    ({'varus_deg': []}, r'varus_deg=\[\] must hold at least one finite angle'),
    ({'varus_deg': [float('nan')]}, r'must hold at least one finite angle'),
    ({'varus_deg': ['left']}, r'is not a list of numbers'),
])
def test_plot_refuses_bad_varus(tmp_path: Path, kwargs: dict[str, Any], match: str) -> None:
    with pytest.raises(ConfigError, match=match) as info:
        plot_table(make_table(), tmp_path / 'plot.png', **kwargs)
    assert '\n' not in str(info.value)
    assert not (tmp_path / 'plot.png').exists()


def test_unwritable_or_wrong_outputs_give_one_line_errors(tmp_path: Path) -> None:
    blocker = tmp_path / 'file'
    blocker.write_text('not a directory')
    table = make_table(varus_deg=(0.0, 0.0, 1))
    for out, match in ((blocker / 'plot.png', r'cannot write picture .*plot\.png'),
                       (tmp_path / 'plot.pdf', r'does not end in \.png')):
        with pytest.raises(KneeseatError, match=match) as info:
            plot_table(table, out)
        assert '\n' not in str(info.value)
    (tmp_path / 'dir.png').mkdir()
    with pytest.raises(KneeseatError, match='cannot write picture') as info:
        plot_table(table, tmp_path / 'dir.png')
    assert not [p for p in tmp_path.iterdir() if p.name.endswith('.tmp')]


@pytest.mark.parametrize('view', ['lateral', 'anterior'])
def test_render_both_views(tmp_path: Path, view: Literal['lateral', 'anterior']) -> None:
    table = make_table()
    out = render_table(table, knee_meshes(), tmp_path / f'{view}.png', view=view)
    image = imread(out)
    panels = 5                                                       # default: 5 of 19 nodes
    assert image.shape[:2] == (round((RENDER_PANEL_IN[1] + RENDER_EXTRA_IN) * DPI),
                               round(panels * RENDER_PANEL_IN[0] * DPI))
    assert image[..., :3].std() > 0.05
    assert png_text(out)[PNG_KEY_NONCONVERGED] == '0'


def test_render_views_differ_and_angles_are_chosen(tmp_path: Path) -> None:
    table = make_table(nonconverged=95)                              # every tibia cell
    meshes = knee_meshes()
    lateral = render_table(table, meshes, tmp_path / 'l.png', flexion_deg=[0, -45, -90])
    anterior = render_table(table, meshes, tmp_path / 'a.png', flexion_deg=[0, -45, -90],
                            view='anterior')
    a, b = imread(lateral), imread(anterior)
    assert a.shape == b.shape
    assert a.shape[1] == round(3 * RENDER_PANEL_IN[0] * DPI)
    assert np.abs(a - b).mean() > 0.01
    assert png_text(lateral)[PNG_KEY_NONCONVERGED] == '3'          # tibia in 3 panels


def test_render_off_grid_flexion_uses_interpolation(tmp_path: Path) -> None:
    """-11 deg lies between the nodes -15 and -10 deg: the render draws the table's
    interpolated poses there (not the nearest node's) and flags the non-converged -15."""
    i15, i10, v0 = 15, 16, 2                         # flexion -15, -10 deg; varus 0 deg
    table = make_table(nonconverged=[(0, i15, v0)])  # the tibia at -15 deg, varus 0
    assert np.degrees(table.flexion_rad[[i15, i10]]) == pytest.approx([-15.0, -10.0])
    assert table.varus_rad[v0] == 0.0
    lookup = table.interpolate(np.radians(-11.0), 0.0)

    def both_nodes_hold(position: np.ndarray, orientation: np.ndarray) -> PoseTable:
        """`table` with each body at this one pose on both nodes around -11 deg."""
        pos, quat = np.array(table.position_m), np.array(table.orientation_xyzw)
        pos[:, [i15, i10]] = np.asarray(position)[:, None, None]
        quat[:, [i15, i10]] = np.asarray(orientation)[:, None, None]
        return PoseTable(table.flexion_rad, table.varus_rad, pos, quat, table.converged,
                         table.iterations, table.metadata)

    meshes = knee_meshes()

    def drawn(which: PoseTable, name: str) -> tuple[np.ndarray, str]:
        out = render_table(which, meshes, tmp_path / name, flexion_deg=[-11.0])
        return imread(out), png_text(out)[PNG_KEY_NONCONVERGED]

    image, flagged = drawn(table, 'table.png')
    assert image.shape[1] == round(RENDER_PANEL_IN[0] * DPI)        # one panel
    assert flagged == '1'             # -15 deg weighs 0.2; the nearest node is converged
    # Around -11 deg, a table whose two nodes both hold the interpolated poses can only
    # draw those; one whose nodes hold the nearest node's (-10 deg) poses draws what a
    # render snapping to the node would. Same titles and flags in all three.
    interpolated, _ = drawn(both_nodes_hold(lookup.position_m, lookup.orientation_xyzw),
                            'interpolated.png')
    nearest, _ = drawn(both_nodes_hold(table.position_m[:, i10, v0],
                                       table.orientation_xyzw[:, i10, v0]), 'nearest.png')
    assert np.abs(image - interpolated).mean() < 1e-4
    assert np.abs(image - nearest).mean() > 1e-2          # the tibia 0.8 mm away: visible


@pytest.mark.parametrize(('kwargs', 'match'), [
    ({'flexion_deg': [10.0]}, r'flexion_deg=10 deg outside the table \[-90, 0\] deg'),
    ({'flexion_deg': [-100.0, -10.0]}, r'flexion_deg=-100 deg outside the table'),
    ({'flexion_deg': [float('inf')]}, r'must hold at least one finite angle'),
    ({'flexion_deg': list(range(-20, 0))}, r'draw at most 12'),
    ({'view': 'posterior'}, r"view='posterior' is not a view; use 'lateral' or 'anterior'"),
])
def test_render_refuses_bad_arguments(tmp_path: Path, kwargs: dict[str, Any],
                                      match: str) -> None:
    with pytest.raises(ConfigError, match=match) as info:
        render_table(make_table(), knee_meshes(1), tmp_path / 'r.png', **kwargs)
    assert '\n' not in str(info.value)


def test_render_refuses_missing_or_unknown_meshes(tmp_path: Path) -> None:
    table = make_table()
    meshes = knee_meshes(1)
    del meshes['patella']
    with pytest.raises(ConfigError, match=r"no mesh for 'patella'"):
        render_table(table, meshes, tmp_path / 'r.png')
    meshes = {**knee_meshes(1), 'fibula': trimesh.creation.box()}
    with pytest.raises(ConfigError, match=r"'fibula', which is not a body of the table"):
        render_table(table, meshes, tmp_path / 'r.png')


def test_render_of_large_meshes_is_quick(tmp_path: Path) -> None:
    """Three meshes of 20k-80k triangles render in well under the 10 s budget."""
    femur = trimesh.creation.icosphere(subdivisions=6, radius=0.025)      # 81,920 faces
    tibia = trimesh.creation.box(extents=[0.045, 0.06, 0.07])
    for _ in range(6):
        tibia = tibia.subdivide()                                          # 49,152 faces
    patella = trimesh.creation.icosphere(subdivisions=5, radius=0.015)    # 20,480 faces
    patella.apply_scale([0.4, 1.0, 1.0])
    started = time.perf_counter()
    render_table(make_table(), {'femur': femur, 'tibia': tibia, 'patella': patella},
                 tmp_path / 'big.png')
    assert time.perf_counter() - started < 10.0


DM = SHARED_DATA / 'tka_dm'


@pytest.mark.slow
def test_render_of_the_real_knee_implants(tmp_path: Path) -> None:
    """The DM implants (24k, 53k, 19k triangles) swing with flexion and render quickly."""
    if not DM.is_dir():
        pytest.skip(f'real knee geometry not found at {DM} (shared data absent)')
    meshes = {'femur': trimesh.load_mesh(DM / 'femoral_component.stl'),
              'tibia': trimesh.load_mesh(DM / 'tibial_insert.stl'),
              'patella': trimesh.load_mesh(DM / 'patellar_button.stl')}
    table = make_table()
    knee = table.axes
    flexion = table.flexion_rad
    spin = np.radians(10.0) * flexion / (np.pi / 2)
    tibia = quat_from_matrix(knee.orientation(flexion, np.zeros_like(flexion), spin))
    patella = quat_from_matrix(knee.orientation(flexion / 2, np.zeros_like(flexion)))
    orientation = np.empty_like(table.orientation_xyzw)
    orientation[0], orientation[1] = tibia[:, None], patella[:, None]
    table = PoseTable(table.flexion_rad, table.varus_rad, np.zeros_like(table.position_m),
                      orientation, table.converged, table.iterations, table.metadata)
    views: tuple[Literal['lateral', 'anterior'], ...] = ('lateral', 'anterior')
    for view in views:
        started = time.perf_counter()
        out = render_table(table, meshes, tmp_path / f'{view}.png', view=view)
        assert time.perf_counter() - started < 10.0
        assert imread(out)[..., :3].std() > 0.05


def test_simplification_keeps_the_shape_within_budget() -> None:
    """Vertex clustering: at most the budget, same bounding box to within a cell or two."""
    from kneeseat_core.report.render import _simplified
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.03)        # 20,480 faces
    vertices, faces, closed = _simplified(sphere, 2000)
    assert closed and 500 < len(faces) <= 2000
    cell = np.sqrt(2.0 * sphere.area / 2000)
    assert np.allclose(vertices.min(axis=0), sphere.bounds[0], atol=2 * cell)
    assert np.allclose(vertices.max(axis=0), sphere.bounds[1], atol=2 * cell)
    radius = np.linalg.norm(vertices, axis=1)
    assert np.all(np.abs(radius - 0.03) < cell)                           # still a sphere


def test_convergence_map_colours_cells_by_reason(tmp_path: Path) -> None:
    table = make_table(nonconverged=4)
    tibia_bad = [tuple(int(k) for k in c) for c in np.argwhere(~np.asarray(table.converged))]
    assert len(tibia_bad) == 4 and {c[0] for c in tibia_bad} == {0}
    codes = {cell: Status.LOST if k % 2 else Status.CAP for k, cell in enumerate(tibia_bad)}
    recorded = make_table(nonconverged=4, statuses=codes)
    out = plot_convergence_map(recorded, tmp_path / 'map.png')
    assert png_text(out)[PNG_KEY_NONCONVERGED] == '4'
    # a table written before reasons were recorded still maps its non-converged cells
    old = plot_convergence_map(table, tmp_path / 'old.png')
    assert png_text(old)[PNG_KEY_NONCONVERGED] == '4'
    # one colour per reason in order of appearance: the first cell's 'iteration cap' red,
    # 'lost contact' orange; without codes all four are 'not converged', red. Each colour
    # fills its cells and a small legend patch.
    red, orange = to_rgb('tab:red'), to_rgb('tab:orange')
    assert pixels_near(old, orange) == 0
    cap, lost, unknown = pixels_near(out, red), pixels_near(out, orange), pixels_near(old, red)
    assert lost == pytest.approx(cap, rel=0.1)                   # two cells each
    assert 0 < cap < 0.6 * unknown                               # two cells of four
    with pytest.raises(ConfigError, match=r'does not end in \.png'):
        plot_convergence_map(table, tmp_path / 'map.jpg')
