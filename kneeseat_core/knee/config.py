"""Knee configuration: bodies, axes, push directions, grid and settle parameters.

A config is YAML (see config/*.yaml). Mesh paths are relative to `mesh_dir`, itself
relative to the config file unless absolute; `--mesh-dir` overrides it. Degrees appear only
in keys ending in `_deg`. Unknown keys are errors (a typo must not be silently ignored).

Attitude of a moving body at grid cell (flexion, varus):
    A = Rot(flexion_axis, flexion_fraction * flexion) @ Rot(varus_axis, varus_fraction * varus)
Its push direction is A @ push, and its settle starts from A applied to the mesh as
delivered (rotation about the push is what settling finds, with the translation). An
optional `locked_slide` (a direction at neutral, turned by A) is a slide the body may not
make: a patella's height along the groove is held by its tendon, not by the push - pushed
onto the sagittally convex trochlea it would otherwise slide off the flange (tried on the
total knee: with any fixed push it leaves the component within 10 degrees of flexion). The
default knee's patella conforms to its trochlea and needs no lock.

Search envelope: a settle may slide a body at most `settle.max_slide_m` across its push and
spin it at most `settle.max_spin_deg` about it, measured from an anchor: in a sweep, the
body's rest at the centre cell carried to the cell's attitude (kneeseat_core/sweep.py);
a cell whose rest lies farther is "not converged" - geometry alone has no rest near that
attitude. A body's own `envelope` ({max_slide_m, max_spin_deg}) makes the envelope hold
instead: it stands in for the soft tissue the patent leaves out, the body rests inside it,
and a rest on its boundary is reported as constrained.

An optional `push_flexion_fraction` turns the push (and the locked slide) with
push_flexion_fraction x flexion instead of the attitude's flexion_fraction x flexion: a
patella's push is the resultant of its quadriceps and patellar-tendon pulls, which turns
more slowly with flexion than the patella itself (docs/natural_knee.md).

A body's `mesh` (and `display_mesh`) is a file name or a list of file names. The collision
meshes of a body are combined into one rigid body (one BVH, contacts per triangle as for
one mesh), e.g. a tibia carrying its cartilage and both menisci. `BodySpec.mesh` is the
first of them; `BodySpec.meshes` holds them all.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
import math
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from kneeseat_core.errors import ConfigError, SettleError, TableError
from kneeseat_core.geometry import KneeAxes, pose_from, rotation_about, TOL, unit
from kneeseat_core.ligaments import LigamentSet, load_ligaments, parse_ligaments
from kneeseat_core.meshes import UNIT_SCALE, Units
from kneeseat_core.params import SettleParams
from kneeseat_core.typed import Floats, Pose

__all__ = ['BodySpec', 'KneeConfig', 'load_config', 'grid_values', 'neutral_pose',
           'config_from_metadata', 'ligaments_from_metadata']


@dataclass(frozen=True, slots=True)
class BodySpec:
    """One body of the knee; `push` and fractions matter for moving bodies only.

    The defaults are a config's: a body without `push` is pushed along +Y, the long axis of
    the knee frame (Y superior), as a tibia below the femur is - unlike `SettleParams.push`,
    the default of a single `kneeseat settle`, which pushes along -Y. A body follows the
    whole flexion and varus unless its fractions say otherwise.
    `mesh` and `display_mesh` are the first collision and display mesh; `meshes` and
    `display_meshes` hold every one (filled from `mesh`/`display_mesh` when not given).
    """

    name: str
    frame: str
    mesh: Path
    display_mesh: Path | None = None
    push: tuple[float, float, float] = (0.0, 1.0, 0.0)
    flexion_fraction: float = 1.0
    varus_fraction: float = 1.0
    locked_slide: tuple[float, float, float] | None = None   # neutral frame, turns with A
    envelope: tuple[float, float] | None = None   # (max slide m, max spin rad) that holds
    meshes: tuple[Path, ...] = ()
    display_meshes: tuple[Path, ...] = ()
    push_flexion_fraction: float | None = None   # None: the push turns with the attitude
    load_n: float | None = None         # the load on the push (N), where ligaments act
    load_toward: tuple[float, float, float] | None = None   # m, reference frame; None: push

    def __post_init__(self) -> None:
        if not self.meshes:
            object.__setattr__(self, 'meshes', (self.mesh,))
        if not self.display_meshes and self.display_mesh is not None:
            object.__setattr__(self, 'display_meshes', (self.display_mesh,))


@dataclass(frozen=True, slots=True, eq=False)
class KneeConfig:
    """A validated knee configuration (SI units; angles in radians)."""

    name: str
    units: Units
    reference: BodySpec
    bodies: tuple[BodySpec, ...]
    axes: KneeAxes
    flexion_rad: Floats          # (F,) ascending
    varus_rad: Floats            # (V,) ascending
    settle: SettleParams         # push is per body; this one's push is ignored
    source: dict[str, Any]       # the config as read (for the table's metadata)
    ligaments: LigamentSet | None = None   # the soft tissue, if the config names it
    # turns computed so far, by (flexion fraction, varus fraction, flexion, varus): a sweep
    # asks each cell's several times (its job, its params, the ribs that learn from it);
    # and the turns about one axis they are made of, by (axis, angle): a grid's few angles
    _turns: dict[tuple[float, float, float, float], Floats] = field(
        default_factory=dict, init=False, repr=False)
    _axis_turns: dict[tuple[str, float], Floats] = field(
        default_factory=dict, init=False, repr=False)

    def attitude(self, body: BodySpec, flexion_rad: float, varus_rad: float) -> Floats:
        """(3, 3) attitude of `body` at a grid cell (module docstring)."""
        return self._turn(body.flexion_fraction, body.varus_fraction, flexion_rad, varus_rad)

    def _turn(self, flexion_fraction: float, varus_fraction: float, flexion_rad: float,
              varus_rad: float) -> Floats:
        """(3, 3) the turn by these fractions of flexion and varus about the knee's axes
        (a copy of the one kept: the caller may change it)."""
        key = (flexion_fraction, varus_fraction, flexion_rad, varus_rad)
        found = self._turns.get(key)
        if found is None:
            found = self._turns[key] = (
                self._axis_turn('flexion', flexion_fraction * flexion_rad)
                @ self._axis_turn('varus', varus_fraction * varus_rad))
        return found.copy()

    def _axis_turn(self, axis: str, angle_rad: float) -> Floats:
        """(3, 3) the turn by `angle_rad` about the knee's `axis` ('flexion' or 'varus'),
        kept (read only)."""
        key = (axis, angle_rad)
        found = self._axis_turns.get(key)
        if found is None:
            found = self._axis_turns[key] = rotation_about(getattr(self.axes, axis), angle_rad)
            found.flags.writeable = False
        return found

    def attitudes(self) -> Floats:
        """(B, F, V, 3, 3) every body's attitude at every grid cell."""
        return np.array([[[self.attitude(body, f, v) for v in self.varus_rad]
                          for f in self.flexion_rad] for body in self.bodies])

    def push_turn(self, body: BodySpec, flexion_rad: float, varus_rad: float) -> Floats:
        """(3, 3) rotation that turns `body`'s neutral push and locked slide at a cell.

        The attitude, unless the body has a `push_flexion_fraction` (module docstring).
        """
        fraction = body.flexion_fraction if body.push_flexion_fraction is None \
            else body.push_flexion_fraction
        return self._turn(fraction, body.varus_fraction, flexion_rad, varus_rad)

    def push(self, body: BodySpec, flexion_rad: float, varus_rad: float) -> Floats:
        """(3,) unit push direction of `body` at a grid cell, reference frame."""
        push: Floats = self.push_turn(body, flexion_rad, varus_rad) @ np.asarray(body.push)
        return push

    def params(self, body: BodySpec, flexion_rad: float, varus_rad: float) -> SettleParams:
        """Settle parameters for `body` at a grid cell."""
        turn = self.push_turn(body, flexion_rad, varus_rad)
        push = turn @ np.asarray(body.push)
        lock = None if body.locked_slide is None else turn @ np.asarray(body.locked_slide)
        changes: dict[str, Any] = {
            'push': (float(push[0]), float(push[1]), float(push[2])),
            'locked_slide': None if lock is None else (float(lock[0]), float(lock[1]),
                                                       float(lock[2]))}
        if body.envelope is not None:
            changes.update(max_slide_m=body.envelope[0], max_spin_rad=body.envelope[1],
                           envelope_holds=True)
        if body.load_n is not None:
            changes.update(load_n=body.load_n, load_toward=body.load_toward)
        return replace(self.settle, **changes)     # one replace: each validates the params

    def placed_before(self, body: BodySpec) -> tuple[str, ...]:
        """The bodies already where they rest when `body` is settled at a cell: the
        reference and the moving bodies before it in the config (a patella's tendon pulls
        from the tibia's settled pose)."""
        names = [self.reference.name] + [b.name for b in self.bodies]
        return tuple(names[:names.index(body.name)])

    def depends_on(self, body: BodySpec) -> tuple[int, ...]:
        """Indices of the moving bodies whose settled poses `body`'s ligaments pull from."""
        if self.ligaments is None:
            return ()
        placed = self.placed_before(body)
        others = {end for f in self.ligaments.acting_on(body.name, placed)
                  for end in f.ends} - {body.name, self.reference.name}
        return tuple(i for i, b in enumerate(self.bodies) if b.name in others)

    def metadata(self) -> dict[str, Any]:
        """The config as plain JSON-able data, with resolved absolute mesh paths."""
        out = dict(self.source)
        out['resolved'] = {
            'reference': _spec_dict(self.reference),
            'bodies': [_spec_dict(b) for b in self.bodies],
            'settle': asdict(self.settle),
            'flexion_deg': [math.degrees(v) for v in self.flexion_rad],
            'varus_deg': [math.degrees(v) for v in self.varus_rad],
            'ligaments': None if self.ligaments is None else {
                'source': self.ligaments.source, 'sha256': self.ligaments.sha256,
                'fibres': len(self.ligaments.fibres), 'bundles': list(self.ligaments.bundles)},
        }
        return out


def neutral_pose(attitude: Floats) -> Pose:
    """(4, 4) a body as delivered, turned by its `attitude` at a cell: the anchor its search
    envelope is measured from."""
    return pose_from(attitude, np.zeros(3))


def config_from_metadata(meta: dict[str, Any]) -> KneeConfig:
    """The knee config a table was built from, rebuilt from its metadata (`resolved` part:
    absolute mesh paths, settle parameters, grid), without reading the YAML again.

    Raises:
        TableError: the metadata lacks the resolved config (a table written without it).
    """
    try:
        resolved = meta['config']['resolved']
        axes = KneeAxes.from_vectors(*(meta['axes'][k] for k in ('flexion', 'varus', 'long')))
        known = set(BodySpec.__dataclass_fields__)
        settle_fields = set(SettleParams.__dataclass_fields__) - {'push', 'locked_slide'}
        settle = replace(_DEFAULTS, **{k: v for k, v in resolved['settle'].items()
                                       if k in settle_fields})
        return KneeConfig(str(meta['config'].get('name', meta.get('name', ''))),
                          meta['config'].get('units', 'm'),
                          _spec_from_dict(resolved['reference'], known),
                          tuple(_spec_from_dict(b, known) for b in resolved['bodies']), axes,
                          np.radians(resolved['flexion_deg']), np.radians(resolved['varus_deg']),
                          settle, dict(meta['config']))
    except (KeyError, TypeError, ValueError) as err:
        raise TableError(f'the table metadata does not hold the config it was built from '
                         f'({type(err).__name__}: {err}); rebuild it with this kneeseat') from None


def _spec_from_dict(data: dict[str, Any], known: set[str]) -> BodySpec:
    d = {k: v for k, v in data.items() if k in known}
    d['mesh'] = Path(d['mesh'])
    d['display_mesh'] = None if d.get('display_mesh') is None else Path(d['display_mesh'])
    d['meshes'] = tuple(Path(m) for m in d.get('meshes') or ())
    d['display_meshes'] = tuple(Path(m) for m in d.get('display_meshes') or ())
    for key in ('push', 'locked_slide', 'envelope', 'load_toward'):
        if d.get(key) is not None:
            d[key] = tuple(float(x) for x in d[key])
    return BodySpec(**d)


def ligaments_from_metadata(meta: dict[str, Any], mesh_dir: Path | None = None
                            ) -> LigamentSet | None:
    """The ligament set a table was built with, read again and checked against the SHA-256
    its metadata records; None for a table built without. `mesh_dir`: where the file is
    now, when it moved with the meshes.

    Raises:
        TableError: the file is missing or holds other ligaments than the table's.
    """
    entry = meta.get('config', {}).get('resolved', {}).get('ligaments')
    if not entry:
        return None
    bodies = [meta['reference']['name']] + [b['name'] for b in meta['bodies']]
    try:
        if entry['source'] == 'inline':
            found = parse_ligaments(meta['config']['ligaments'], 'ligaments', bodies,
                                    meta['config'].get('units', 'm'))
        else:
            path = Path(entry['source'])
            found = load_ligaments(Path(mesh_dir) / path.name if mesh_dir else path, bodies)
    except ConfigError as err:
        raise TableError(f"the table's ligaments cannot be read: {err}") from None
    if found.sha256 != entry['sha256']:
        raise TableError(f'{found.source} holds other ligaments than the table was built with '
                         f"(SHA-256 {found.sha256[:12]}, the table's {entry['sha256'][:12]}); "
                         'pass --mesh-dir with the folder of the original file')
    return found


def _spec_dict(spec: BodySpec) -> dict[str, Any]:
    d = asdict(spec)
    d['mesh'] = str(spec.mesh)
    d['display_mesh'] = None if spec.display_mesh is None else str(spec.display_mesh)
    d['meshes'] = [str(m) for m in spec.meshes]
    d['display_meshes'] = [str(m) for m in spec.display_meshes]
    return d


_TOP_KEYS = {'name', 'units', 'mesh_dir', 'reference', 'axes', 'bodies', 'grid', 'settle',
             'ligaments'}
_BODY_KEYS = {'name', 'frame', 'mesh', 'display_mesh', 'push', 'flexion_fraction',
              'varus_fraction', 'locked_slide', 'envelope', 'push_flexion_fraction', 'load_n',
              'load_toward'}
_ENVELOPE_KEYS = {'max_slide_m', 'max_spin_deg'}
_REF_KEYS = {'name', 'frame', 'mesh', 'display_mesh'}
_GRID_KEYS = {'flexion_deg', 'varus_deg'}
_SETTLE_KEYS = {'step_m', 'resolution_m', 'rotation_step_deg', 'rotation_resolution_deg',
                'max_iterations', 'max_slide_m', 'max_spin_deg', 'method'}


def _check_keys(data: Any, allowed: set[str], where: str, required: set[str]) -> None:
    if not isinstance(data, dict):
        raise ConfigError(f'{where} must be a mapping of keys, got {type(data).__name__}')
    unknown = sorted(set(data) - allowed)
    if unknown:
        raise ConfigError(f'{where}: unknown key {unknown[0]!r}; allowed: '
                          f'{", ".join(sorted(allowed))}')
    missing = sorted(required - set(data))
    if missing:
        raise ConfigError(f'{where}: missing key {missing[0]!r}')


def grid_values(spec: Any, where: str) -> Floats:
    """[start, stop, step] in degrees -> ascending radians (stop included)."""
    if (not isinstance(spec, (list, tuple)) or len(spec) != 3
            or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in spec)):
        raise ConfigError(f'{where} must be [start, stop, step] in degrees, got {spec!r}')
    start, stop, step = (float(v) for v in spec)
    if start == stop:
        return np.array([math.radians(start)])
    if step == 0:
        raise ConfigError(f'{where}: step must not be zero')
    count = abs(stop - start) / abs(step)
    if abs(count - round(count)) > TOL.grid_step:
        raise ConfigError(f'{where}: step {abs(step):g} does not divide {start:g}..{stop:g}; '
                          'choose a step that lands on stop')
    if round(count) + 1 > 100_000:
        raise ConfigError(f'{where}: {round(count) + 1} grid values is too many')
    values = np.linspace(start, stop, int(round(count)) + 1)
    return np.radians(np.sort(values))


def _point(value: Any, where: str, scale: float) -> tuple[float, float, float]:
    """Three finite numbers, in the config's units -> metres."""
    if not (isinstance(value, list) and len(value) == 3
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
                    for v in value)):
        raise ConfigError(f'{where} must be three numbers like [0.04, 0.25, 0.01], got '
                          f'{value!r}')
    return float(value[0]) * scale, float(value[1]) * scale, float(value[2]) * scale


def _vector(value: Any, where: str) -> tuple[float, float, float]:
    try:
        vec = unit(np.asarray(value, dtype=float), where)
    except (TypeError, ValueError):
        raise ConfigError(f'{where} must be three numbers like [0, 1, 0], got {value!r}') \
            from None
    return float(vec[0]), float(vec[1]), float(vec[2])


def _number(value: Any, where: str) -> float:
    if not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ConfigError(f'{where} must be a number, got {value!r}')
    return float(value)


def _mesh_path(mesh_dir: Path, value: Any, where: str) -> Path:
    if not isinstance(value, str) or not value:
        raise ConfigError(f'{where} must be a file name, got {value!r}')
    path = Path(value) if Path(value).is_absolute() else mesh_dir / value
    if not path.is_file():
        raise ConfigError(f'{where}: mesh file {path} not found; fix the path or pass '
                          '--mesh-dir DIR')
    return path


def _mesh_paths(mesh_dir: Path, value: Any, where: str) -> tuple[Path, ...]:
    """A file name or a non-empty list of distinct file names -> paths."""
    if not isinstance(value, list):
        return (_mesh_path(mesh_dir, value, where),)
    if not value:
        raise ConfigError(f'{where} must be a file name or a non-empty list of file names, '
                          'got []')
    paths = tuple(_mesh_path(mesh_dir, v, f'{where}[{i}]') for i, v in enumerate(value))
    if len(set(p.resolve() for p in paths)) != len(paths):
        raise ConfigError(f'{where} lists a mesh twice ({value}); give each file once')
    return paths


def _body(data: Any, mesh_dir: Path, where: str, moving: bool, units: Units = 'm'
          ) -> BodySpec:
    _check_keys(data, _BODY_KEYS if moving else _REF_KEYS, where, {'name', 'mesh'})
    name = data['name']
    if not isinstance(name, str) or not name.isidentifier():
        raise ConfigError(f'{where}.name must be a simple identifier (letters, digits, _), '
                          f'got {name!r}')
    display = data.get('display_mesh')
    meshes = _mesh_paths(mesh_dir, data['mesh'], f'{where}.mesh')
    displays = () if display is None else _mesh_paths(mesh_dir, display,
                                                      f'{where}.display_mesh')
    spec = BodySpec(name=name, frame=str(data.get('frame', name)), mesh=meshes[0],
                    display_mesh=displays[0] if displays else None, meshes=meshes,
                    display_meshes=displays)
    if not moving:
        return spec
    given: dict[str, Any] = {}       # keys left out keep BodySpec's defaults
    if 'push' in data:
        given['push'] = _vector(data['push'], f'{where}.push')
    for key in ('flexion_fraction', 'varus_fraction'):
        if key in data:
            given[key] = _number(data[key], f'{where}.{key}')
    if data.get('load_n') is not None:
        given['load_n'] = _number(data['load_n'], f'{where}.load_n')
        if given['load_n'] <= 0.0:
            raise ConfigError(f'{where}.load_n={given["load_n"]:g} must be a positive number '
                              'of newtons')
    if data.get('load_toward') is not None:
        given['load_toward'] = _point(data['load_toward'], f'{where}.load_toward',
                                      UNIT_SCALE[units])
    push_fraction = data.get('push_flexion_fraction')
    return replace(spec, **given,
                   locked_slide=(None if data.get('locked_slide') is None else
                                 _vector(data['locked_slide'], f'{where}.locked_slide')),
                   envelope=(None if data.get('envelope') is None else
                             _envelope(data['envelope'], f'{where}.envelope')),
                   push_flexion_fraction=(None if push_fraction is None else _number(
                       push_fraction, f'{where}.push_flexion_fraction')))


def _envelope(data: Any, where: str) -> tuple[float, float]:
    """A body's envelope that holds: (max slide m, max spin rad), both required."""
    _check_keys(data, _ENVELOPE_KEYS, where, _ENVELOPE_KEYS)
    slide = _number(data['max_slide_m'], f'{where}.max_slide_m')
    spin = _number(data['max_spin_deg'], f'{where}.max_spin_deg')
    if not 0.0 < slide <= 0.1:
        raise ConfigError(f'{where}.max_slide_m={slide:g} must be in (0, 0.1] m')
    if not 0.0 < spin <= 180.0:
        raise ConfigError(f'{where}.max_spin_deg={spin:g} must be in (0, 180] degrees')
    return slide, math.radians(spin)


_DEFAULTS = SettleParams()


def _settle_number(data: dict[str, Any], key: str, whole: bool = False) -> float | None:
    """`settle.key` of the config as a number (a whole one where `whole`), or None where
    it is absent or null."""
    value = data.get(key)
    if value is None:
        return None
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = math.nan
    if isinstance(value, bool) or math.isnan(number) or (whole and not number.is_integer()):
        raise ConfigError(f'settle.{key} must be a {"whole " if whole else ""}number, got '
                          f'{value!r}')
    return number


def _settle_params(data: Any) -> SettleParams:
    if isinstance(data, dict) and 'travel' in data:
        raise ConfigError('settle: travel is no longer a setting (the default method measures '
                          'the travel exactly); remove the key')
    _check_keys(data, _SETTLE_KEYS, 'settle', set())

    def number(key: str, default: float, whole: bool = False) -> float:
        value = _settle_number(data, key, whole)
        return default if value is None else value

    def angle(key: str) -> float | None:
        degrees = _settle_number(data, key)
        return None if degrees is None else math.radians(degrees)

    spin = angle('max_spin_deg')
    params = SettleParams(
        step_m=number('step_m', _DEFAULTS.step_m),
        resolution_m=number('resolution_m', _DEFAULTS.resolution_m),
        rotation_step_rad=angle('rotation_step_deg'),
        rotation_resolution_rad=angle('rotation_resolution_deg'),
        max_iterations=int(number('max_iterations', _DEFAULTS.max_iterations, whole=True)),
        max_slide_m=number('max_slide_m', _DEFAULTS.max_slide_m),
        max_spin_rad=_DEFAULTS.max_spin_rad if spin is None else spin,
        method=data.get('method', _DEFAULTS.method))
    try:
        params.check()
    except SettleError as err:  # re-label as a config problem
        raise ConfigError(f'settle: {err}') from None
    return params


def load_config(path: Path, mesh_dir: Path | None = None,
                overrides: dict[str, Any] | None = None) -> KneeConfig:
    """Read and validate a knee config.

    Args:
        path: YAML file.
        mesh_dir: overrides the config's `mesh_dir`.
        overrides: top-level sections merged in before validation, key by key within a
            section (e.g. {'grid': {'flexion_deg': [...]}} keeps the file's varus grid).
    Raises:
        ConfigError: unreadable YAML, unknown or missing keys, missing meshes, zero-length
            or non-orthogonal axes, bad grid or settle values; the message names the key.
    """
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f'{path}: no such config file') from None
    except (OSError, yaml.YAMLError) as err:
        raise ConfigError(f'{path}: not readable YAML ({str(err).splitlines()[0]})') from None
    if overrides:
        data = dict(data or {})
        for key, value in overrides.items():
            section = data.get(key)
            if isinstance(value, dict) and isinstance(section, dict):
                value = {**section, **value}
            data[key] = value
    try:
        return _parse(data, path, mesh_dir)
    except ConfigError as err:
        raise ConfigError(f'{path}: {err}') from None


def _parse(data: Any, path: Path, mesh_dir: Path | None) -> KneeConfig:
    _check_keys(data, _TOP_KEYS, 'config', {'reference', 'axes', 'bodies', 'grid'})
    units = data.get('units', 'm')
    if units not in UNIT_SCALE:
        raise ConfigError(f"units must be 'm' or 'mm', got {units!r}")
    if mesh_dir is None:
        mesh_dir = Path(data.get('mesh_dir', '.'))
        if not mesh_dir.is_absolute():
            mesh_dir = path.parent / mesh_dir
    mesh_dir = mesh_dir.resolve()
    if not mesh_dir.is_dir():
        raise ConfigError(f'mesh_dir {mesh_dir} is not a directory; pass --mesh-dir DIR')
    axes_data = data['axes']
    _check_keys(axes_data, {'flexion', 'varus', 'long'}, 'axes', {'flexion', 'varus', 'long'})
    axes = KneeAxes.from_vectors(*(np.asarray(_vector(axes_data[k], f'axes.{k}'))
                                   for k in ('flexion', 'varus', 'long')))
    reference = _body(data['reference'], mesh_dir, 'reference', moving=False)
    bodies_data = data['bodies']
    if not isinstance(bodies_data, list) or not bodies_data:
        raise ConfigError('bodies must be a non-empty list of moving bodies')
    bodies = tuple(_body(b, mesh_dir, f'bodies[{i}]', moving=True, units=units)
                   for i, b in enumerate(bodies_data))
    names = [reference.name] + [b.name for b in bodies]
    if len(set(names)) != len(names):
        raise ConfigError(f'body names must be unique, got {names}')
    grid = data['grid']
    _check_keys(grid, _GRID_KEYS, 'grid', _GRID_KEYS)
    settle = _settle_params(data.get('settle') or {})
    name = str(data.get('name', path.stem))
    ligaments = _ligaments(data.get('ligaments'), mesh_dir, names, units)
    config = KneeConfig(name, units, reference, bodies, axes,
                        grid_values(grid['flexion_deg'], 'grid.flexion_deg'),
                        grid_values(grid['varus_deg'], 'grid.varus_deg'), settle, data,
                        ligaments)
    for i, body in enumerate(bodies):
        acting = [] if ligaments is None else \
            ligaments.acting_on(body.name, config.placed_before(body))
        if acting and body.load_n is None:
            raise ConfigError(f'bodies[{i}].load_n: {len(acting)} ligament fibres act on '
                              f'{body.name!r}; give the load on its push in newtons')
    return config


def _ligaments(value: Any, mesh_dir: Path, bodies: list[str], units: str
               ) -> LigamentSet | None:
    """`ligaments:` a file in the shared format (relative to mesh_dir, like the meshes) or
    a list of fibres inline."""
    if value is None:
        return None
    if isinstance(value, list):
        return parse_ligaments(value, 'ligaments', bodies, units)
    if not isinstance(value, str) or not value:
        raise ConfigError(f'ligaments must be a file name or a list of fibres, got {value!r}')
    path = Path(value) if Path(value).is_absolute() else mesh_dir / value
    return load_ligaments(path, bodies)
