"""`python -m kneeseat_ros.demo --out DIR`: the whole pipeline on the default or natural knee.

Phases (each timed; `scripts/demo` runs `scripts/setup` first and passes its time in):

1. table: `--knee default` (the default) writes the embedded knee's meshes into
   `DIR/default_knee/`; `--knee natural` uses `config/natural_knee.yaml` with the natural
   knee's meshes (its `mesh_dir`, or `--mesh-dir`; without them the demo stops with one
   line, exit code 2). The table `DIR/<config name>_<step>deg.npz` is built on a
   `step`-degree grid (2 by default, so that a fresh machine stays well under 3 minutes;
   `--full-grid` uses the patent's 1 degree). A table that is already there is reused
   when `read_table` accepts it, it was built from these meshes and it has the requested
   grid; otherwise it is rebuilt.
2. server: `table_server` as a child process with `record:=DIR/sessions`; ready when its
   first `/diagnostics` message arrives (the demo subscribes to it).
3. replay: `replay` of the shipped angle bag `data/angle_bags/gait_demo` (10 s gait cycle,
   100 Hz PoseStamped on /knee/pose) with `--wait-for-subscribers 1`; without the repo
   the same bag is regenerated into `DIR/angle_bags/gait_demo`. The demo then waits until
   the server's diagnostics show every replayed message received (or stop changing).
4. stop: SIGINT to the server, which must exit 0 (its bag is then finalised).
5. read: the new session bag (mcap reader + mcap_ros2 decoder): inputs, outputs, the last
   diagnostics. Latency per answer = log_time of the last body's output - log_time of the
   input with the same stamp (both node clock; replay re-publishes the bag's old stamps, so
   the node's own stamp-based latency does not apply). Every output is also checked
   against `PoseTable.interpolate` of its input.
6. plot: `DIR/demo_session.png`, per moving body the translations (mm) and the spin about
   the long axis (deg) of the recorded outputs against the input's flexion (decoded with
   the table's axes), with the table's curve at varus 0.
7. summary on stdout: messages in/out/dropped, latency p50/p99, paths, timings.

Exit codes: 0 done; 1 the demo failed (one line `demo: error: ...` on stderr); 2 bad
arguments. The server and the replay are always stopped before the demo exits.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
import math
import os
from pathlib import Path
import signal
import subprocess
import sys
import time
from typing import Any, IO

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
import numpy as np

from kneeseat_core.build import build_table, executor_for, materialise_default_knee
from kneeseat_core.errors import ConfigError, KneeseatError, MeshError, TableError
from kneeseat_core.geometry import matrix_from_quat, TOL
from kneeseat_core.knee import KneeConfig, load_config
from kneeseat_core.plots import write_png
from kneeseat_core.sweep import default_workers
from kneeseat_core.table import PoseTable
from kneeseat_core.table_io import read_table
from kneeseat_core.typed import Floats
from kneeseat_ros import topics
from kneeseat_ros.conversions import stamp_ns
from kneeseat_ros.errors import DataMissing, DemoError

__all__ = ['DemoError', 'DataMissing', 'KNEES', 'NATURAL_CONFIG', 'DEFAULT_OUT',
           'DEFAULT_STEP_DEG', 'PLOT_NAME', 'PLOT_SIZE_PX',
           'SessionStats', 'prepare_table', 'demo_bag', 'read_session', 'plot_session',
           'run', 'main']

DEFAULT_OUT = Path('out') / 'demo'
DEFAULT_STEP_DEG = 2.0                 # 46 x 11 grid: about a quarter of the full build
FLEXION_RANGE_DEG = (0.0, -90.0)       # the patent's knee grid
VARUS_RANGE_DEG = (-10.0, 10.0)
PLOT_NAME = 'demo_session.png'
PLOT_DPI = 100
PLOT_SIZE_PX = (1400, 900)             # (width, height) of the session PNG
MIN_SPIN_SPAN_DEG = 1.0                # spin axes show at least this range
SHIPPED_BAG = Path(__file__).resolve().parents[1] / 'data' / 'angle_bags' / 'gait_demo'
NATURAL_CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'natural_knee.yaml'
KNEES = ('default', 'natural')
POSE_TOPIC = topics.at_root(topics.POSE)
SERVER_READY_TIMEOUT_S = 60.0          # first /diagnostics after the server starts
SUBSCRIBER_TIMEOUT_S = 60.0            # replay --wait-timeout-s
DRAIN_TIMEOUT_S = 20.0                 # after the replay: until every input is counted
STOP_TIMEOUT_S = 20.0                  # SIGINT -> exit of the server
_SPIN_SLICE_S = 0.05


class _Stop(Exception):
    """SIGTERM reached the demo: unwind (children are stopped in `finally`)."""


# ----------------------------------------------------------------------------- phase 1


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


# ----------------------------------------------------------------------------- phase 3
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
    from kneeseat_ros.make_bag import DEFAULT_START_NS, gait, write_angle_bag
    from kneeseat_ros.replay import load_messages
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


# ------------------------------------------------------------------------- processes
def _child_env() -> dict[str, str]:
    """Environment of the ROS children (and of the demo's own rclpy)."""
    env = dict(os.environ)
    prefixes = [p for p in env.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    if sys.prefix not in prefixes:
        prefixes.insert(0, sys.prefix)
    env['AMENT_PREFIX_PATH'] = os.pathsep.join(prefixes)
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env.setdefault('ROS_DOMAIN_ID', str(os.getpid() % 100 + 1))
    env['PYTHONUNBUFFERED'] = '1'
    return env


def _last_line(log: Path) -> str:
    try:
        lines = [ln.strip() for ln in log.read_text(errors='replace').splitlines() if ln.strip()]
    except OSError:
        return ''
    return lines[-1] if lines else ''


def _stop_child(proc: subprocess.Popen[Any] | None, timeout_s: float) -> int | None:
    """SIGINT, then SIGTERM, then SIGKILL; returns the exit code of the first clean exit."""
    if proc is None:
        return None
    if proc.poll() is not None:
        return proc.returncode
    for sig in (signal.SIGINT, signal.SIGTERM):
        proc.send_signal(sig)
        try:
            return proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            continue
    proc.kill()
    proc.wait()
    return None


class _Monitor:
    """An rclpy node of the demo's own listening to /diagnostics of its server."""

    def __init__(self, table_path: Path) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSDurabilityPolicy, QoSProfile, QoSReliabilityPolicy
        from rclpy.signals import SignalHandlerOptions
        from diagnostic_msgs.msg import DiagnosticArray
        self._rclpy = rclpy
        self.context = Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node('kneeseat_demo', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.values: dict[str, str] = {}
        self.count = 0
        self._table = str(table_path)
        qos = QoSProfile(depth=10, reliability=QoSReliabilityPolicy.RELIABLE,
                         durability=QoSDurabilityPolicy.VOLATILE)
        self.node.create_subscription(DiagnosticArray, topics.DIAGNOSTICS, self._on_diag, qos)

    def _on_diag(self, msg: Any) -> None:
        for status in msg.status:
            values = {kv.key: kv.value for kv in status.values}
            # another server on this ROS domain serves another table: not ours
            if status.name == topics.STATUS_NAME and values.get('table') == self._table:
                self.values = values
                self.count += 1

    def spin_until(self, done: Callable[[], bool], timeout_s: float,
                   alive: Callable[[], None]) -> bool:
        """Spin until `done()`; False at the deadline. `alive()` raises if a child died."""
        deadline = time.monotonic() + timeout_s
        while not done():
            alive()
            if time.monotonic() > deadline:
                return False
            self.executor.spin_once(timeout_sec=_SPIN_SLICE_S)
        return True

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.context)


@contextmanager
def _sigterm_unwinds() -> Iterator[None]:
    """SIGTERM raises `_Stop` in the main thread, so `finally` blocks stop the children."""
    def raise_stop(*_: Any) -> None:
        raise _Stop
    previous = signal.signal(signal.SIGTERM, raise_stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


# ----------------------------------------------------------------------------- phase 5
@dataclass(frozen=True, slots=True, eq=False)
class SessionStats:
    """What one recorded session holds, matched input -> outputs by header stamp."""

    bag: Path
    bodies: tuple[str, ...]
    inputs: int                           # /knee/pose messages recorded (received)
    outputs: int                          # /knee/<body>/pose messages recorded
    answered: int                         # inputs with an output for every body
    diagnostics: int                      # /diagnostics messages recorded
    last_diagnostics: dict[str, str]      # key -> value of the last server status
    input_quat: Floats                    # (n, 4) xyzw of the answered inputs
    position_m: Floats                    # (n, B, 3) m, reference frame
    orientation_xyzw: Floats              # (n, B, 4)
    latency_ns: Floats                    # (n,) last output log_time - input log_time
    time_range_ns: tuple[int, int]        # first and last log_time in the bag

    def latency_ms(self, q: float) -> float:
        """Percentile `q` (0..100) of the answer latency in ms; NaN without answers."""
        if not self.latency_ns.size:
            return math.nan
        return float(np.percentile(self.latency_ns, q)) * 1e-6


def read_session(bag: Path, bodies: Sequence[str]) -> SessionStats:
    """Read a session bag written by table_server (mcap reader, mcap_ros2 decoder).

    Args:
        bag: the session directory (metadata.yaml + .mcap files).
        bodies: moving body names; outputs are read from /knee/<body>/pose.
    Raises:
        KneeseatError: the bag cannot be read (replay.BagError).
    """
    from kneeseat_ros.replay import bag_files
    out_topics = {topics.at_root(topics.body_pose(b)): i for i, b in enumerate(bodies)}
    inputs: dict[int, tuple[int, tuple[float, float, float, float]]] = {}
    outputs: dict[int, dict[int, tuple[int, list[float], list[float]]]] = {}
    n_out = n_diag = 0
    last: dict[str, str] = {}
    first_ns, last_ns = None, None
    for path in bag_files(bag):
        with open(path, 'rb') as stream:
            reader = make_reader(stream, decoder_factories=[DecoderFactory()])
            for _, channel, message, msg in reader.iter_decoded_messages(log_time_order=True):
                t = int(message.log_time)
                first_ns = t if first_ns is None else min(first_ns, t)
                last_ns = t if last_ns is None else max(last_ns, t)
                topic = channel.topic
                if topic == POSE_TOPIC:
                    o = msg.pose.orientation
                    inputs[stamp_ns(msg.header.stamp)] = (t, (o.x, o.y, o.z, o.w))
                elif topic in out_topics:
                    n_out += 1
                    p, o = msg.pose.position, msg.pose.orientation
                    outputs.setdefault(stamp_ns(msg.header.stamp), {})[out_topics[topic]] = (
                        t, [p.x, p.y, p.z], [o.x, o.y, o.z, o.w])
                elif topic == topics.DIAGNOSTICS:
                    n_diag += 1
                    for status in msg.status:
                        if status.name == topics.STATUS_NAME:
                            last = {kv.key: kv.value for kv in status.values}
    quats, pos, ori, lat = [], [], [], []
    for stamp, (t_in, quat) in sorted(inputs.items()):
        answer = outputs.get(stamp, {})
        if len(answer) != len(bodies):
            continue
        quats.append(quat)
        pos.append([answer[i][1] for i in range(len(bodies))])
        ori.append([answer[i][2] for i in range(len(bodies))])
        lat.append(max(answer[i][0] for i in range(len(bodies))) - t_in)
    nb = len(bodies)
    return SessionStats(
        bag=bag, bodies=tuple(bodies), inputs=len(inputs), outputs=n_out, answered=len(quats),
        diagnostics=n_diag, last_diagnostics=last,
        input_quat=np.asarray(quats, dtype=np.float64).reshape(-1, 4),
        position_m=np.asarray(pos, dtype=np.float64).reshape(-1, nb, 3),
        orientation_xyzw=np.asarray(ori, dtype=np.float64).reshape(-1, nb, 4),
        latency_ns=np.asarray(lat, dtype=np.float64),
        time_range_ns=(first_ns or 0, last_ns or 0))


def table_deviation(session: SessionStats, table: PoseTable) -> tuple[float, float]:
    """Largest |output - table.interpolate(input)|: (position m, quaternion component)."""
    flexion, varus, _ = table.axes.decompose(matrix_from_quat(session.input_quat))
    dp = dq = 0.0
    for k, (f, v) in enumerate(zip(flexion.tolist(), varus.tolist())):
        look = table.interpolate(f, v)
        dp = max(dp, float(np.abs(session.position_m[k] - look.position_m).max()))
        dq = max(dq, float(np.abs(session.orientation_xyzw[k] - look.orientation_xyzw).max()))
    return dp, dq


# ----------------------------------------------------------------------------- phase 6
_XYZ_COLOURS = ('tab:blue', 'tab:orange', 'tab:green')


def plot_session(session: SessionStats, table: PoseTable, out: Path) -> Path:
    """Write the recorded outputs against flexion, with the table at varus 0, as a PNG.

    Per moving body (rows): translations x, y, z (mm, reference frame) and the spin about
    the long axis (deg) against the input's flexion (deg), recorded outputs as dots and
    `table.interpolate(flexion, 0)` as lines. Written atomically; `PLOT_SIZE_PX` pixels.

    Raises:
        DemoError: no answered input to draw, or the file cannot be written.
    """
    if session.answered == 0:
        raise DemoError(f'session {session.bag} has no answered input to plot; check the '
                        'server log in the demo directory')
    axes = table.axes
    flex_in, varus_in, _ = axes.decompose(matrix_from_quat(session.input_quat))
    flex_in_deg = np.degrees(flex_in)
    spin_out = np.degrees(axes.decompose(matrix_from_quat(session.orientation_xyzw))[2])
    lo, hi = float(table.flexion_rad[0]), float(table.flexion_rad[-1])
    curve_rad = np.linspace(lo, hi, 181)
    varus0 = min(max(0.0, float(table.varus_rad[0])), float(table.varus_rad[-1]))
    looks = [table.interpolate(f, varus0) for f in curve_rad.tolist()]
    curve_pos = np.stack([lk.position_m for lk in looks]) * 1e3                # (m, B, 3)
    curve_spin = np.degrees(axes.decompose(matrix_from_quat(
        np.stack([lk.orientation_xyzw for lk in looks])))[2])                  # (m, B)
    curve_deg = np.degrees(curve_rad)

    nb = len(session.bodies)
    fig = Figure(figsize=(PLOT_SIZE_PX[0] / PLOT_DPI, PLOT_SIZE_PX[1] / PLOT_DPI),
                 dpi=PLOT_DPI, layout='constrained')
    FigureCanvasAgg(fig)
    grid = fig.subplots(nb, 2, squeeze=False)
    for b, body in enumerate(session.bodies):
        ax_t, ax_s = grid[b]
        for c, (name, colour) in enumerate(zip('xyz', _XYZ_COLOURS)):
            ax_t.plot(curve_deg, curve_pos[:, b, c], color=colour, lw=1.5,
                      label=f'{name} table (varus {math.degrees(varus0):g} deg)')
            ax_t.scatter(flex_in_deg, session.position_m[:, b, c] * 1e3, s=4, color=colour,
                         alpha=0.5, edgecolors='none', label=f'{name} recorded')
        ax_s.plot(curve_deg, curve_spin[:, b], color='tab:purple', lw=1.5,
                  label=f'table (varus {math.degrees(varus0):g} deg)')
        ax_s.scatter(flex_in_deg, spin_out[:, b], s=4, color='tab:purple', alpha=0.5,
                     edgecolors='none', label='recorded')
        ax_t.set_title(f'{body}: translation in {table.reference_frame!r}')
        ax_s.set_title(f'{body}: spin about the long axis')
        ax_t.set_ylabel('mm')
        ax_s.set_ylabel('deg')
        _min_span(ax_s, np.concatenate([curve_spin[:, b], spin_out[:, b]]), MIN_SPIN_SPAN_DEG)
        for ax in (ax_t, ax_s):
            ax.set_xlabel('flexion (deg, negative = flexed)')
            ax.set_xlim(math.degrees(lo), math.degrees(hi))
            ax.grid(True, alpha=0.3)
        ax_t.legend(fontsize=7, ncol=3, loc='best', markerscale=3)
        ax_s.legend(fontsize=7, loc='best', markerscale=3)
    fig.suptitle(f'kneeseat demo session {session.bag.name}: {session.answered} answers '
                 f'(input varus {np.degrees(varus_in).min():.1f}..'
                 f'{np.degrees(varus_in).max():.1f} deg), table {table.metadata.get("name", "")} '
                 f'{len(table.flexion_rad)} x {len(table.varus_rad)}')
    return write_png(fig, Path(out))


def _min_span(ax: Any, values: Floats, span: float) -> None:
    """Show at least `span` on the y axis, so that round-off does not look like motion."""
    lo, hi = float(np.min(values)), float(np.max(values))
    if hi - lo < span:
        mid = 0.5 * (lo + hi)
        ax.set_ylim(mid - 0.5 * span, mid + 0.5 * span)


# ---------------------------------------------------------------------------- driver
def _diag_int(values: dict[str, str], key: str) -> int:
    try:
        return int(values.get(key, '0'))
    except ValueError:
        return 0


def _new_session(sessions: Path, before: set[Path]) -> Path:
    new = sorted(p for p in sessions.glob('kneeseat_*') if p.is_dir() and p not in before)
    if not new:
        raise DemoError(f'the server wrote no session bag under {sessions}; see its log')
    return new[-1]


def run(args: argparse.Namespace) -> int:
    """Run every phase (see the module docstring); print where everything is."""
    t_start = time.monotonic()
    timings: dict[str, float] = {}
    if args.setup_s is not None:
        timings['setup'] = args.setup_s
    out: Path = args.out.expanduser().absolute()
    out.mkdir(parents=True, exist_ok=True)
    env = _child_env()
    os.environ.update(env)           # the demo's own rclpy uses the same domain and index
    step = 1.0 if args.full_grid else args.grid_step_deg
    print(f'demo: output in {out}, ROS_DOMAIN_ID={env["ROS_DOMAIN_ID"]}', flush=True)

    from kneeseat_ros.replay import load_messages
    if args.bag is not None:
        load_messages(args.bag, [POSE_TOPIC])        # a bad --bag fails before the build
    t = time.monotonic()
    table_path, table, how = prepare_table(out, step, args.workers, not args.quiet,
                                           args.knee, args.mesh_dir)
    timings['table'] = time.monotonic() - t
    print(f'demo: table {table_path} ({how}, {timings["table"]:.1f} s)', flush=True)
    bag = args.bag if args.bag is not None else demo_bag(out, table)
    sent = len(load_messages(bag, [POSE_TOPIC]))

    sessions = out / 'sessions'
    sessions.mkdir(exist_ok=True)
    logs = out / 'logs'
    logs.mkdir(exist_ok=True)
    stamp = time.strftime('%Y%m%d_%H%M%S')
    server_log = logs / f'table_server_{stamp}.log'
    before = set(sessions.iterdir())
    server: subprocess.Popen[Any] | None = None
    replay: subprocess.Popen[Any] | None = None
    monitor: _Monitor | None = None
    log_stream: IO[bytes] | None = None
    try:
        t = time.monotonic()
        monitor = _Monitor(table_path)
        log_stream = open(server_log, 'wb')
        server = subprocess.Popen(
            [sys.executable, '-m', 'kneeseat_ros.table_server', '--ros-args',
             '-p', f'table:={table_path}', '-p', f'record:={sessions}'],
            stdout=log_stream, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env)

        def server_alive() -> None:
            if server is not None and server.poll() is not None:
                raise DemoError(f'table_server exited with code {server.returncode}: '
                                f'{_last_line(server_log)!r} (log {server_log})')

        if not monitor.spin_until(lambda: monitor is not None and monitor.count > 0,
                                  SERVER_READY_TIMEOUT_S, server_alive):
            raise DemoError(f'table_server sent no /diagnostics within '
                            f'{SERVER_READY_TIMEOUT_S:g} s; see {server_log}')
        timings['server start'] = time.monotonic() - t
        print(f'demo: table_server ready ({timings["server start"]:.1f} s), recording into '
              f'{sessions}; replaying {bag} at x{args.rate:g}', flush=True)

        t = time.monotonic()
        replay = subprocess.Popen(
            [sys.executable, '-m', 'kneeseat_ros.replay', str(bag), '--rate', f'{args.rate}',
             '--topics', POSE_TOPIC, '--wait-for-subscribers', '1',
             '--wait-timeout-s', f'{SUBSCRIBER_TIMEOUT_S:g}'],
            stdin=subprocess.DEVNULL, env=env)
        monitor.spin_until(lambda: replay is not None and replay.poll() is not None,
                           math.inf, server_alive)
        if replay.returncode != 0:
            raise DemoError(f'replay of {bag} exited with code {replay.returncode} (see its '
                            'message above)')
        timings['replay'] = time.monotonic() - t

        t = time.monotonic()
        seen = [monitor.count, -1]

        def drained() -> bool:
            assert monitor is not None
            received = _diag_int(monitor.values, 'received')
            if received >= sent:
                return True
            if monitor.count >= seen[0] + 2:     # two full periods after the replay ended
                if received == seen[1]:
                    return True
                seen[0], seen[1] = monitor.count, received
            return False

        monitor.spin_until(drained, DRAIN_TIMEOUT_S, server_alive)
        proc, server = server, None
        code = _stop_child(proc, STOP_TIMEOUT_S)
        if code != 0:
            raise DemoError(f'table_server did not stop cleanly on SIGINT (exit code {code}); '
                            f'its bag may be unfinished; see {server_log}')
        timings['stop'] = time.monotonic() - t
    finally:
        _stop_child(replay, STOP_TIMEOUT_S)
        _stop_child(server, STOP_TIMEOUT_S)
        if monitor is not None:
            monitor.close()
        if log_stream is not None:
            log_stream.close()

    t = time.monotonic()
    session_bag = _new_session(sessions, before)
    session = read_session(session_bag, table.bodies)
    dev_m, dev_q = table_deviation(session, table)
    timings['read'] = time.monotonic() - t
    t = time.monotonic()
    png = plot_session(session, table, out / PLOT_NAME)
    timings['plot'] = time.monotonic() - t
    timings['total'] = time.monotonic() - t_start + timings.get('setup', 0.0)
    _print_summary(sent, session, dev_m, dev_q, table_path, table, how, bag, png, server_log,
                   timings)
    if session.answered == 0:
        raise DemoError(f'the server answered none of the {sent} replayed messages; see '
                        f'{server_log}')
    return 0


def _print_summary(sent: int, s: SessionStats, dev_m: float, dev_q: float, table_path: Path,
                   table: PoseTable, how: str, bag: Path, png: Path, server_log: Path,
                   timings: dict[str, float]) -> None:
    d = s.last_diagnostics
    dropped = _diag_int(d, 'dropped')
    clamped = _diag_int(d, 'clamped')
    per_body = s.outputs / max(len(s.bodies), 1)
    lines = [
        'kneeseat demo summary',
        f'  table        {table_path} ({len(table.flexion_rad)} x {len(table.varus_rad)} grid, '
        f'bodies {", ".join(table.bodies)}; {how})',
        f'  replayed     {bag} ({sent} messages on {POSE_TOPIC})',
        f'  messages     in {s.inputs} (of {sent} sent; {sent - s.inputs} never taken by the '
        f'node), out {s.outputs} ({per_body:g} per body), answered {s.answered}, '
        f'dropped {dropped}, clamped {clamped}',
        f'  latency      p50 {s.latency_ms(50):.3f} ms, p99 {s.latency_ms(99):.3f} ms, max '
        f'{s.latency_ms(100):.3f} ms (input received -> last body published, from bag '
        'log times)',
        f'  check        outputs vs table.interpolate(input): max {dev_m:.2e} m, '
        f'{dev_q:.2e} (quaternion)',
        f'  bag          {s.bag} ({s.inputs + s.outputs + s.diagnostics} messages, '
        f'{(s.time_range_ns[1] - s.time_range_ns[0]) * 1e-9:.1f} s)',
        f'  plot         {png}',
        f'  server log   {server_log}',
        '  timings      ' + ', '.join(f'{k} {v:.1f} s' for k, v in timings.items()),
    ]
    print('\n'.join(lines), flush=True)


def _step_arg(text: str) -> float:
    try:
        step = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number of degrees") from None
    ratio = 10.0 / step if step > 0 and math.isfinite(step) else 0.0
    if not ratio or abs(ratio - round(ratio)) > TOL.demo_step:
        raise argparse.ArgumentTypeError(f'{text} deg does not divide 10 deg; use 1, 2, 5 '
                                         'or 10 (or 0.5)')
    return step


def build_parser() -> argparse.ArgumentParser:
    """The `python -m kneeseat_ros.demo` command line."""
    p = argparse.ArgumentParser(
        prog='demo', description='Full kneeseat demo on a knee: build the table, serve it '
        'with recording on, replay the gait angle bag through it, then summarise and plot '
        'the recorded session.')
    p.add_argument('--out', type=Path, default=DEFAULT_OUT,
                   help=f'demo directory (default {DEFAULT_OUT})')
    p.add_argument('--knee', choices=KNEES, default='default',
                   help='default: the embedded procedural knee; natural: the natural knee '
                   '(config/natural_knee.yaml; needs its meshes)')
    p.add_argument('--mesh-dir', type=Path, default=None,
                   help="directory of the natural knee meshes (default: the config's "
                   'mesh_dir)')
    grid = p.add_mutually_exclusive_group()
    grid.add_argument('--grid-step-deg', type=_step_arg, default=DEFAULT_STEP_DEG,
                      help=f'table grid step in degrees (default {DEFAULT_STEP_DEG:g}: a '
                      'quarter of the full build, well under 3 minutes on 2 cores)')
    grid.add_argument('--full-grid', action='store_true',
                      help="the patent's 1-degree grid (91 x 21; about 4x longer to build)")
    p.add_argument('--workers', type=int, default=default_workers(),
                   help=f'build processes (default: all cores, here {default_workers()})')
    p.add_argument('--rate', type=float, default=1.0,
                   help='replay speed factor (default 1: the 10 s bag takes 10 s)')
    p.add_argument('--bag', type=Path, default=None,
                   help='angle bag to replay (default: the shipped gait_demo bag)')
    p.add_argument('--setup-s', type=float, default=None,
                   help='seconds scripts/setup took (shown in the timings)')
    p.add_argument('--quiet', action='store_true', help='no build progress bar')
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of `python -m kneeseat_ros.demo`; returns the exit code."""
    args = build_parser().parse_args(argv)
    if args.workers < 1 or not (args.rate > 0 and math.isfinite(args.rate)):
        print('demo: error: --workers must be >= 1 and --rate a positive number; fix the '
              'option', file=sys.stderr)
        return 2
    try:
        with _sigterm_unwinds():
            return run(args)
    except DataMissing as err:
        print(f'demo: error: {err}', file=sys.stderr)
        return 2
    except KneeseatError as err:
        print(f'demo: error: {err}', file=sys.stderr)
        return 1
    except (KeyboardInterrupt, _Stop):
        print('demo: error: interrupted; the server and the replay were stopped',
              file=sys.stderr)
        return 130


if __name__ == '__main__':
    sys.exit(main())
