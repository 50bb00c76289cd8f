"""`python -m kneeseat_ros.demos.demo --out DIR`: the whole pipeline on the default or natural
knee.

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

Phase 1 is `kneeseat_ros.demos.demo_table`, the children and the diagnostics listener
`kneeseat_ros.demos.children`, reading the session `kneeseat_ros.bag.session`, the picture
`kneeseat_core.report.plots.plot_session`; each phase is one function here.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
import math
import os
from pathlib import Path
import subprocess
import sys
import time
from typing import Any, IO

from kneeseat_core.args import default_workers, worker_count
from kneeseat_core.errors import KneeseatError
from kneeseat_core.geometry import TOL
from kneeseat_core.report import plots
from kneeseat_core.table import PoseTable
from kneeseat_ros.bag.session import POSE_TOPIC, read_session, SessionStats, table_deviation
from kneeseat_ros.demos.children import (child_env, DiagnosticsMonitor, last_line, sigterm_unwinds,
                                         Stop, stop_child)
from kneeseat_ros.demos.demo_table import DEFAULT_STEP_DEG, demo_bag, KNEES, prepare_table
from kneeseat_ros.errors import DataMissing, DemoError

__all__ = ['DEFAULT_OUT', 'PLOT_NAME', 'plot_session', 'run', 'main']

DEFAULT_OUT = Path('out') / 'demo'
PLOT_NAME = 'demo_session.png'
SERVER_READY_TIMEOUT_S = 60.0          # first /diagnostics after the server starts
SUBSCRIBER_TIMEOUT_S = 60.0            # replay --wait-timeout-s
DRAIN_TIMEOUT_S = 20.0                 # after the replay: until every input is counted
STOP_TIMEOUT_S = 20.0                  # SIGINT -> exit of the server


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


@dataclass(slots=True, eq=False)
class _Run:
    """One demo run: where things are, what was sent, how long each phase took."""

    out: Path
    env: dict[str, str]
    timings: dict[str, float]
    table_path: Path = Path()
    table: PoseTable | None = None
    how: str = ''                     # 'built' or 'reused ...'
    bag: Path = Path()
    sent: int = 0                     # messages in the bag on POSE_TOPIC
    sessions: Path = Path()
    server_log: Path = Path()
    before: set[Path] = field(default_factory=set)    # session bags before the server ran

    def served(self) -> PoseTable:
        """The table (phase 1 done)."""
        assert self.table is not None
        return self.table


def _phase_table(args: argparse.Namespace, run: _Run) -> None:
    """Phase 1: build or reuse the table; find the bag to replay."""
    from kneeseat_ros.bag.replay import load_messages
    sent = None
    if args.bag is not None:                         # a bad --bag fails before the build
        sent = len(load_messages(args.bag, [POSE_TOPIC]))
    step = 1.0 if args.full_grid else args.grid_step_deg
    t = time.monotonic()
    run.table_path, run.table, run.how = prepare_table(run.out, step, args.workers,
                                                       not args.quiet, args.knee,
                                                       args.mesh_dir)
    run.timings['table'] = time.monotonic() - t
    print(f'demo: table {run.table_path} ({run.how}, {run.timings["table"]:.1f} s)',
          flush=True)
    run.bag = args.bag if args.bag is not None else demo_bag(run.out, run.table)
    run.sent = len(load_messages(run.bag, [POSE_TOPIC])) if sent is None else sent
    run.sessions = run.out / 'sessions'
    run.sessions.mkdir(exist_ok=True)
    logs = run.out / 'logs'
    logs.mkdir(exist_ok=True)
    run.server_log = logs / f'table_server_{time.strftime("%Y%m%d_%H%M%S")}.log'
    run.before = set(run.sessions.iterdir())


def _phase_server(run: _Run, monitor: DiagnosticsMonitor, log_stream: IO[bytes]
                  ) -> subprocess.Popen[Any]:
    """Phase 2: start table_server with recording on; ready at its first /diagnostics."""
    t = time.monotonic()
    server = subprocess.Popen(
        [sys.executable, '-m', 'kneeseat_ros.table_server', '--ros-args',
         '-p', f'table:={run.table_path}', '-p', f'record:={run.sessions}'],
        stdout=log_stream, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=run.env)
    if not monitor.spin_until(lambda: monitor.count > 0, SERVER_READY_TIMEOUT_S,
                              _alive(server, run.server_log)):
        raise DemoError(f'table_server sent no /diagnostics within '
                        f'{SERVER_READY_TIMEOUT_S:g} s; see {run.server_log}')
    run.timings['server start'] = time.monotonic() - t
    return server


def _phase_replay(args: argparse.Namespace, run: _Run, monitor: DiagnosticsMonitor,
                  server: subprocess.Popen[Any]) -> subprocess.Popen[Any]:
    """Phase 3: replay the bag through the server (returns the finished replay)."""
    print(f'demo: table_server ready ({run.timings["server start"]:.1f} s), recording into '
          f'{run.sessions}; replaying {run.bag} at x{args.rate:g}', flush=True)
    t = time.monotonic()
    replay = subprocess.Popen(
        [sys.executable, '-m', 'kneeseat_ros.bag.replay', str(run.bag), '--rate', f'{args.rate}',
         '--topics', POSE_TOPIC, '--wait-for-subscribers', '1',
         '--wait-timeout-s', f'{SUBSCRIBER_TIMEOUT_S:g}'],
        stdin=subprocess.DEVNULL, env=run.env)
    monitor.spin_until(lambda: replay.poll() is not None, math.inf,
                       _alive(server, run.server_log))
    if replay.returncode != 0:
        raise DemoError(f'replay of {run.bag} exited with code {replay.returncode} (see its '
                        'message above)')
    run.timings['replay'] = time.monotonic() - t
    return replay


def _phase_stop(run: _Run, monitor: DiagnosticsMonitor, server: subprocess.Popen[Any]) -> None:
    """Phase 4: wait until the server counted every input (or stopped counting), then
    SIGINT it; it must exit 0 (its bag is then finalised)."""
    t = time.monotonic()
    seen = [monitor.count, -1]

    def drained() -> bool:
        received = _diag_int(monitor.values, 'received')
        if received >= run.sent:
            return True
        if monitor.count >= seen[0] + 2:     # two full periods after the replay ended
            if received == seen[1]:
                return True
            seen[0], seen[1] = monitor.count, received
        return False

    monitor.spin_until(drained, DRAIN_TIMEOUT_S, _alive(server, run.server_log))
    code = stop_child(server, STOP_TIMEOUT_S)
    if code != 0:
        raise DemoError(f'table_server did not stop cleanly on SIGINT (exit code {code}); '
                        f'its bag may be unfinished; see {run.server_log}')
    run.timings['stop'] = time.monotonic() - t


def _alive(server: subprocess.Popen[Any], log: Path) -> Callable[[], None]:
    """A check that raises DemoError once `server` has exited."""
    def check() -> None:
        if server.poll() is not None:
            raise DemoError(f'table_server exited with code {server.returncode}: '
                            f'{last_line(log)!r} (log {log})')
    return check


def _phases_with_children(args: argparse.Namespace, run: _Run) -> None:
    """Phases 2-4; the server and the replay are always stopped before this returns."""
    server: subprocess.Popen[Any] | None = None
    replay: subprocess.Popen[Any] | None = None
    monitor: DiagnosticsMonitor | None = None
    try:
        with open(run.server_log, 'wb') as log_stream:
            monitor = DiagnosticsMonitor(run.table_path)
            server = _phase_server(run, monitor, log_stream)
            replay = _phase_replay(args, run, monitor, server)
            proc, server = server, None
            _phase_stop(run, monitor, proc)
    finally:
        stop_child(replay, STOP_TIMEOUT_S)
        stop_child(server, STOP_TIMEOUT_S)
        if monitor is not None:
            monitor.close()


def _phase_read_and_plot(run: _Run) -> tuple[SessionStats, float, float, Path]:
    """Phases 5 and 6: read the new session bag, check it against the table, plot it."""
    table = run.served()
    t = time.monotonic()
    session = read_session(_new_session(run.sessions, run.before), table.bodies)
    dev_m, dev_q = table_deviation(session, table)
    run.timings['read'] = time.monotonic() - t
    t = time.monotonic()
    png = plot_session(session, table, run.out / PLOT_NAME)
    run.timings['plot'] = time.monotonic() - t
    return session, dev_m, dev_q, png


def run(args: argparse.Namespace) -> int:
    """Run every phase (see the module docstring); print where everything is."""
    t_start = time.monotonic()
    out: Path = args.out.expanduser().absolute()
    out.mkdir(parents=True, exist_ok=True)
    env = child_env()
    os.environ.update(env)           # the demo's own rclpy uses the same domain and index
    run = _Run(out, env, {} if args.setup_s is None else {'setup': args.setup_s})
    print(f'demo: output in {out}, ROS_DOMAIN_ID={env["ROS_DOMAIN_ID"]}', flush=True)
    _phase_table(args, run)
    _phases_with_children(args, run)
    session, dev_m, dev_q, png = _phase_read_and_plot(run)
    run.timings['total'] = time.monotonic() - t_start + run.timings.get('setup', 0.0)
    _print_summary(run, session, dev_m, dev_q, png)
    return 0


def plot_session(session: SessionStats, table: PoseTable, out: Path) -> Path:
    """The demo's picture of `session` (`kneeseat_core.report.plots.plot_session`).

    Raises:
        DemoError: no answered input to draw.
        ConfigError: the file cannot be written.
    """
    if session.answered == 0:
        raise DemoError(f'session {session.bag} has no answered input to plot; check the '
                        'server log in the demo directory')
    return plots.plot_session(table, session.input_quat, session.position_m,
                              session.orientation_xyzw, out,
                              name=f'kneeseat demo session {session.bag.name}')


def _print_summary(run: _Run, s: SessionStats, dev_m: float, dev_q: float, png: Path) -> None:
    table, sent = run.served(), run.sent
    d = s.last_diagnostics
    per_body = s.outputs / max(len(s.bodies), 1)
    lines = [
        'kneeseat demo summary',
        f'  table        {run.table_path} ({len(table.flexion_rad)} x '
        f'{len(table.varus_rad)} grid, bodies {", ".join(table.bodies)}; {run.how})',
        f'  replayed     {run.bag} ({sent} messages on {POSE_TOPIC})',
        f'  messages     in {s.inputs} (of {sent} sent; {sent - s.inputs} never taken by the '
        f'node), out {s.outputs} ({per_body:g} per body), answered {s.answered}, '
        f'dropped {_diag_int(d, "dropped")}, clamped {_diag_int(d, "clamped")}',
        f'  latency      p50 {s.latency_ms(50):.3f} ms, p99 {s.latency_ms(99):.3f} ms, max '
        f'{s.latency_ms(100):.3f} ms (input received -> last body published, from bag '
        'log times)',
        f'  check        outputs vs table.interpolate(input): max {dev_m:.2e} m, '
        f'{dev_q:.2e} (quaternion)',
        f'  bag          {s.bag} ({s.inputs + s.outputs + s.diagnostics} messages, '
        f'{(s.time_range_ns[1] - s.time_range_ns[0]) * 1e-9:.1f} s)',
        f'  plot         {png}',
        f'  server log   {run.server_log}',
        '  timings      ' + ', '.join(f'{k} {v:.1f} s' for k, v in run.timings.items()),
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
    """The `python -m kneeseat_ros.demos.demo` command line."""
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
    p.add_argument('--workers', type=worker_count, default=default_workers(),
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
    """Entry point of `python -m kneeseat_ros.demos.demo`; returns the exit code."""
    args = build_parser().parse_args(argv)
    if not (args.rate > 0 and math.isfinite(args.rate)):
        print('demo: error: --rate must be a positive number; fix the option',
              file=sys.stderr)
        return 2
    try:
        with sigterm_unwinds():
            return run(args)
    except DataMissing as err:
        print(f'demo: error: {err}', file=sys.stderr)
        return 2
    except KneeseatError as err:
        print(f'demo: error: {err}', file=sys.stderr)
        return 1
    except (KeyboardInterrupt, Stop):
        print('demo: error: interrupted; the server and the replay were stopped',
              file=sys.stderr)
        return 130


if __name__ == '__main__':
    sys.exit(main())
