"""`python -m kneeseat_ros.demos.tracker_demo --out DIR`: tracker mode end to end, with a picture.

A synthetic motion capture session: a leg walks a curve through the world (the whole leg
translates and turns) while the knee flexes and bends; two marker clusters, one on the
thigh and one on the shank, are tracked in the world frame. The demo

1. writes a registration file `DIR/registration.yaml` (each bone's frame in its cluster's
   frame: a few centimetres off and turned, as a real registration is),
2. starts `table_server` in tracker mode (child process) on a table (`--table`, or the
   embedded default knee's table built or reused as `python -m kneeseat_ros.demos.demo` does),
3. publishes both clusters' PoseStamped at `--rate-hz` (same stamp per pair) and collects
   every `knee/<bone>/world_pose` answer,
4. compares each answer with the composition computed here with 4 x 4 matrices
   (world_T_cluster * registration, KneeAxes.decompose of the relative tibia-in-femur
   rotation, PoseTable.interpolate, world_T_femur * table pose) and prints the largest
   position and rotation error,
5. draws `DIR/tracker_world.png`: top and side views of the world with the bones' origins
   and axes along the path (from the node's answers).

Exit codes: 0 done (errors within 1e-9); 1 the node failed or an error exceeds 1e-9;
2 bad arguments.
"""
from __future__ import annotations

import argparse
from collections.abc import Callable, Sequence
from dataclasses import dataclass
import functools
from pathlib import Path
import subprocess
import sys
import time
from typing import Any

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
import numpy as np
from scipy.spatial.transform import Rotation
import yaml

from kneeseat_core.errors import KneeseatError
from kneeseat_core.geometry import KneeAxes
from kneeseat_core.report.plots import write_png
from kneeseat_core.table import PoseTable, read_table
from kneeseat_core.typed import Floats, Poses
from kneeseat_ros import topics
from kneeseat_ros.conversions import display_mesh_paths
from kneeseat_ros.demos.children import child_env, stop_child

__all__ = ['leg_motion', 'example_registration', 'registration_yaml', 'expected_world',
           'pose_matrix', 'main', 'MAX_ERROR']

# The node's answers must equal the composition computed here to this (m, and quaternion
# components): the same arithmetic in another order differs by round-off only.
MAX_ERROR = 1e-9


def pose_matrix(position: Sequence[float] | Floats, quat_xyzw: Sequence[float] | Floats) -> Floats:
    """(4, 4) pose from a position (m) and a quaternion (x, y, z, w)."""
    out = np.eye(4)
    out[:3, :3] = Rotation.from_quat(np.asarray(quat_xyzw, dtype=np.float64)).as_matrix()
    out[:3, 3] = position
    return out


def _quat(rotation: Floats) -> Floats:
    """(x, y, z, w), w >= 0, of a (3, 3) rotation."""
    return np.asarray(Rotation.from_matrix(rotation).as_quat(canonical=True))


def _rot(axis: Sequence[float], angle: float | Floats) -> Floats:
    """Rotations (3, 3) or (n, 3, 3) about `axis` by `angle` (rad, scalar or (n,))."""
    k = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    return Rotation.from_rotvec(np.multiply.outer(angle, k)).as_matrix()


def leg_motion(axes: KneeAxes, n: int, duration_s: float = 4.0,
               flexion_range_rad: tuple[float, float] = (-1.5, 0.0),
               varus_range_rad: tuple[float, float] = (-0.15, 0.15),
               seed: int = 0) -> tuple[Poses, Poses, Floats]:
    """World poses of the femur and tibia bone frames while the leg moves.

    The femur walks 1.5 m along a curve, turning about the vertical and swaying; the tibia's
    orientation in the femur frame is `axes.orientation(flexion, varus, rotation)` with a
    gait-like flexion, a varus wobble and some screw-home rotation; its origin sits 0.4 m
    down the long axis.

    Returns:
        femur (n, 4, 4), tibia (n, 4, 4) world poses (m), and the (n, 3) true flexion,
        varus and rotation (rad).
    """
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, duration_s, n)
    phase = 2.0 * np.pi * t / duration_s
    f_lo, f_hi = flexion_range_rad
    v_lo, v_hi = varus_range_rad
    flexion = f_lo + (f_hi - f_lo) * (0.5 + 0.5 * np.cos(2.0 * phase))
    varus = v_lo + (v_hi - v_lo) * (0.5 + 0.5 * np.sin(3.0 * phase + rng.uniform(0, 1)))
    rotation = 0.1 * np.sin(phase)
    femur = np.tile(np.eye(4), (n, 1, 1))
    heading = 0.6 * np.sin(phase / 2.0)
    femur[:, :3, :3] = (_rot([0.0, 0.0, 1.0], heading) @ _rot([1.0, 0.0, 0.0], 0.2 *
                        np.sin(phase)) @ _rot([1.0, 0.0, 0.0], np.pi / 2))
    femur[:, :3, 3] = np.stack([1.5 * t / duration_s, 0.4 * np.sin(phase / 2.0),
                                0.9 + 0.03 * np.sin(2.0 * phase)], -1)
    rel = np.tile(np.eye(4), (n, 1, 1))
    rel[:, :3, :3] = axes.orientation(flexion, varus, rotation)
    rel[:, :3, 3] = -0.4 * axes.long
    return femur, femur @ rel, np.stack([flexion, varus, rotation], -1)


def example_registration(seed: int = 1) -> tuple[Floats, Floats]:
    """Cluster -> bone poses (4, 4) for femur and tibia: a few cm off and turned."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(2):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        out.append(pose_matrix(rng.uniform(-0.08, 0.08, 3), q))
    return out[0], out[1]


def registration_yaml(femur: Floats, tibia: Floats) -> str:
    """The registration file's text for two (4, 4) cluster -> bone poses."""
    def entry(m: Floats) -> dict[str, list[float]]:
        return {'translation': [float(v) for v in m[:3, 3]],
                'rotation': [float(v) for v in _quat(m[:3, :3])]}
    return yaml.safe_dump({'femur': entry(femur), 'tibia': entry(tibia)}, sort_keys=False)


def expected_world(table: PoseTable, femur_cluster: Floats, tibia_cluster: Floats,
                   reg_femur: Floats, reg_tibia: Floats) -> tuple[Floats, list[Floats]]:
    """What tracker mode must answer for one pair, with 4 x 4 matrices.

    Returns:
        world_T_femur (4, 4) and world_T_body (4, 4) per moving body.
    """
    femur = femur_cluster @ reg_femur
    tibia = tibia_cluster @ reg_tibia
    flexion, varus, _ = table.axes.decompose(femur[:3, :3].T @ tibia[:3, :3])
    lookup = table.interpolate(float(flexion), float(varus))
    bodies = zip(lookup.position_m, lookup.orientation_xyzw)
    return femur, [femur @ pose_matrix(p, q) for p, q in bodies]


def _pose_error(got: Any, want: Floats) -> tuple[float, float]:
    """(position error m, largest quaternion component error up to sign) of a PoseStamped."""
    p, o = got.pose.position, got.pose.orientation
    q = np.array([o.x, o.y, o.z, o.w])
    qw = _quat(want[:3, :3])
    return (float(np.abs(np.array([p.x, p.y, p.z]) - want[:3, 3]).max()),
            float(min(np.abs(q - qw).max(), np.abs(q + qw).max())))


@dataclass(frozen=True, slots=True, eq=False)
class _Walk:
    """The synthetic session: the table, the registration and the clusters' world poses."""

    table_path: Path
    table: PoseTable
    registration: Path
    reg_femur: Floats            # (4, 4) femur cluster -> femur
    reg_tibia: Floats            # (4, 4) tibia cluster -> tibia
    femur_cluster: Poses         # (n, 4, 4) world poses
    tibia_cluster: Poses
    names: tuple[str, ...]       # the reference, then the moving bodies


def _prepare(args: argparse.Namespace) -> _Walk:
    """Steps 1 and the motion: table, registration file, the clusters' world poses."""
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    if args.table is not None:
        table_path, table = args.table, read_table(args.table)
    else:
        from kneeseat_ros.demos.demo_table import prepare_table
        table_path, table, why = prepare_table(out, 2.0, 2)
        print(f'tracker_demo: default knee table {table_path}: {why}')
    reg_f, reg_t = example_registration()
    registration = out / 'registration.yaml'
    registration.write_text(registration_yaml(reg_f, reg_t))
    f_range = (float(table.flexion_rad[0]), float(table.flexion_rad[-1]))
    v_range = (float(table.varus_rad[0]) * 0.8, float(table.varus_rad[-1]) * 0.8)
    femur, tibia, _ = leg_motion(table.axes, args.samples, args.samples / args.rate_hz,
                                 f_range, v_range)
    return _Walk(table_path, table, registration, reg_f, reg_t, femur @ np.linalg.inv(reg_f),
                 tibia @ np.linalg.inv(reg_t),
                 (str(table.metadata['reference']['name']), *table.bodies))


class _Tracker:
    """The demo's own rclpy node: publishes the clusters, collects the world poses."""

    def __init__(self, walk: _Walk, env: dict[str, str], server: subprocess.Popen[Any],
                 log: Path) -> None:
        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, QoSReliabilityPolicy
        from rclpy.signals import SignalHandlerOptions

        from geometry_msgs.msg import PoseStamped
        self._rclpy, self.walk, self.server, self.log = rclpy, walk, server, log
        self.context = Context()
        rclpy.init(context=self.context, domain_id=int(env['ROS_DOMAIN_ID']),
                   signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node('tracker_demo', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        reliable = QoSProfile(depth=100, reliability=QoSReliabilityPolicy.RELIABLE)
        self.pubs = [self.node.create_publisher(PoseStamped, topic, reliable)
                     for topic in (topics.TRACKER_FEMUR, topics.TRACKER_TIBIA)]
        self.answers: dict[tuple[str, int], Any] = {}
        for name in walk.names:
            self.node.create_subscription(PoseStamped, topics.body_world_pose(name),
                                          functools.partial(self._store, name), reliable)

    def _store(self, name: str, msg: Any) -> None:
        from kneeseat_ros.conversions import stamp_ns
        self.answers[(name, stamp_ns(msg.header.stamp))] = msg

    def spin_until(self, done: Callable[[], bool], timeout_s: float, what: str) -> None:
        """Spin until `done()`; KneeseatError when the server died or time ran out."""
        deadline = time.monotonic() + timeout_s
        while not done():
            if self.server.poll() is not None or time.monotonic() > deadline:
                raise KneeseatError(f'{what} did not happen; server log: {self.log}')
            self.executor.spin_once(timeout_sec=0.02)

    def publish(self, k: int, stamp_ns_: int) -> None:
        """Both clusters' world poses of sample `k`, stamped `stamp_ns_`."""
        from kneeseat_ros.conversions import pose_stamped, stamp_from_ns
        stamp = stamp_from_ns(stamp_ns_)
        for pub, m in zip(self.pubs, (self.walk.femur_cluster[k], self.walk.tibia_cluster[k])):
            pub.publish(pose_stamped(m[:3, 3], _quat(m[:3, :3]), stamp, 'world'))

    def warm_up(self) -> None:
        """Wait for discovery; the first best-effort samples after it can be lost, so send
        the first pose with fresh stamps (earlier than the session) until one is answered."""
        names = self.walk.names
        self.spin_until(lambda: all(p.get_subscription_count() for p in self.pubs)
                        and all(self.node.count_publishers(topics.body_world_pose(n))
                                for n in names), 30.0, 'discovery of table_server')
        warm_ns = time.time_ns()
        deadline = time.monotonic() + 30.0
        while not any(key[1] < warm_ns + 10**9 for key in self.answers):
            if self.server.poll() is not None or time.monotonic() > deadline:
                raise KneeseatError(f'no answer to the warm-up pairs; server log: {self.log}')
            self.publish(0, time.time_ns())
            self.executor.spin_once(timeout_sec=0.1)
        self.answers.clear()

    def session(self, samples: int, rate_hz: float) -> list[int]:
        """Send every pair and wait for each answer; returns the stamps (ns)."""
        start_ns = time.time_ns() + 10**9
        stamps = []
        for k in range(samples):
            stamps.append(start_ns + int(k * 1e9 / rate_hz))
            self.publish(k, stamps[-1])

            def answered(key: int = stamps[-1]) -> bool:
                return all((n, key) in self.answers for n in self.walk.names)

            self.spin_until(answered, 10.0, f'the answer to pair {k}')
        return stamps

    def close(self) -> None:
        """Destroy the node and its context."""
        self.executor.shutdown()
        self.node.destroy_node()
        self._rclpy.try_shutdown(context=self.context)


def _compare(walk: _Walk, answers: dict[tuple[str, int], Any],
             stamps: list[int]) -> tuple[float, float, Floats]:
    """Largest position and quaternion error of the answers against `expected_world`, and
    every answer as (names, samples, 4, 4) world poses."""
    pos_err = rot_err = 0.0
    worlds = np.zeros((len(walk.names), len(stamps), 4, 4))
    for k, key in enumerate(stamps):
        want_f, want_b = expected_world(walk.table, walk.femur_cluster[k],
                                        walk.tibia_cluster[k], walk.reg_femur, walk.reg_tibia)
        for i, (name, want) in enumerate(zip(walk.names, [want_f, *want_b])):
            got = answers[(name, key)]
            e_p, e_q = _pose_error(got, want)
            pos_err, rot_err = max(pos_err, e_p), max(rot_err, e_q)
            p, o = got.pose.position, got.pose.orientation
            worlds[i, k] = pose_matrix((p.x, p.y, p.z), (o.x, o.y, o.z, o.w))
    return pos_err, rot_err, worlds


def _run(args: argparse.Namespace) -> int:
    walk = _prepare(args)
    env = child_env()
    log = args.out / 'tracker_server.log'
    with open(log, 'wb') as stream:
        server = subprocess.Popen(
            [str(Path(sys.prefix) / 'bin' / 'table_server'), '--ros-args', '-p',
             f'table:={walk.table_path}', '-p', f'tracker.registration:={walk.registration}'],
            stdout=stream, stderr=subprocess.STDOUT, env=env)
    tracker: _Tracker | None = None
    try:
        tracker = _Tracker(walk, env, server, log)
        tracker.warm_up()
        stamps = tracker.session(args.samples, args.rate_hz)
        pos_err, rot_err, worlds = _compare(walk, tracker.answers, stamps)
    finally:
        if tracker is not None:
            tracker.close()
        rc = stop_child(server, 15.0)
    png = plot_world(worlds, walk.names, args.out / 'tracker_world.png',
                     _mesh_points(walk.table, walk.table_path))
    print(f'tracker_demo: {args.samples} pairs at {args.rate_hz:g} Hz through table_server '
          f'(exit {rc}); every answer arrived; largest error against the composition of '
          f'the inputs, the registration and the table: position {pos_err:.2e} m, '
          f'quaternion component {rot_err:.2e}; picture {png}')
    return 0 if max(pos_err, rot_err) <= MAX_ERROR and rc == 0 else 1


def _mesh_points(table: PoseTable, table_path: Path,
                 count: int = 400) -> list[Floats] | None:
    """Up to `count` vertices (m) of each body's mesh (reference first), or None.

    The mesh paths come from the table's metadata (relative ones from the table's folder);
    a table whose meshes are not on this machine is drawn with frames only.
    """
    from kneeseat_core.errors import MeshError
    from kneeseat_core.meshes import load_meshes
    meta = table.metadata
    units = meta.get('config', {}).get('units', 'm')
    points = []
    for entry in (meta['reference'], *meta['bodies']):
        paths = display_mesh_paths(entry, table_path.parent)
        if not paths:
            return None
        try:
            vertices = np.asarray(load_meshes(paths, units).vertices)
        except MeshError:
            return None
        step = max(len(vertices) // count, 1)
        points.append(vertices[::step])
    return points


def plot_world(worlds: Floats, names: Sequence[str], out: Path,
               meshes: list[Floats] | None = None) -> Path:
    """Top and side views of the bones along the path: frames, and mesh points if given.

    Args:
        worlds: (bodies, samples, 4, 4) world poses, reference body first.
        meshes: per body, (n, 3) mesh vertices in its own frame (m), drawn at a few poses.
    """
    fig = Figure(figsize=(11, 5.5))
    FigureCanvasAgg(fig)
    colours = ('#444444', '#c0392b', '#2471a3', '#229954')
    n = worlds.shape[1]
    every = max(n // 12, 1)
    for col, (view, (a, b)) in enumerate((('top (x, y)', (0, 1)), ('side (x, z)', (0, 2)))):
        ax = fig.add_subplot(1, 2, col + 1)
        for i, name in enumerate(names):
            path = worlds[i, :, :3, 3]
            ax.plot(path[:, a], path[:, b], color=colours[i % 4], lw=1.2, label=name)
            for k in range(0, n, every):
                origin, rot = worlds[i, k, :3, 3], worlds[i, k, :3, :3]
                for axis, style in zip(range(3), ('r', 'g', 'b')):
                    tip = origin + 0.05 * rot[:, axis]
                    ax.plot([origin[a], tip[a]], [origin[b], tip[b]], style, lw=0.8)
        for k in range(0, n, every):       # the leg: femur origin -> each body origin
            for i in range(1, len(names)):
                seg = worlds[[0, i], k, :3, 3]
                ax.plot(seg[:, a], seg[:, b], color='#999999', lw=0.6)
        if meshes is not None:             # the bones themselves at a few instants
            for k in range(0, n, max(n // 5, 1)):
                for i, pts in enumerate(meshes):
                    world = pts @ worlds[i, k, :3, :3].T + worlds[i, k, :3, 3]
                    ax.scatter(world[:, a], world[:, b], s=0.6, color=colours[i % 4],
                               alpha=0.5, linewidths=0)
        ax.set_title(f'world, {view} (m)')
        ax.set_aspect('equal', adjustable='datalim')
        ax.grid(alpha=0.3)
        if col == 0:
            ax.legend(loc='best', fontsize=8)
    fig.suptitle('table_server tracker mode: bones in the world frame while the leg moves '
                 '(frames: x red, y green, z blue, 5 cm; dots: mesh vertices at 5 instants)',
                 fontsize=10)
    fig.tight_layout()
    return write_png(fig, out)


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; see the module docstring."""
    parser = argparse.ArgumentParser(prog='python -m kneeseat_ros.demos.tracker_demo',
                                     description=__doc__.split('\n\n')[0])
    parser.add_argument('--out', type=Path, default=Path('out/tracker_demo'))
    parser.add_argument('--table', type=Path, default=None,
                        help='a table file; default: the embedded knee (built or reused)')
    parser.add_argument('--samples', type=int, default=200)
    parser.add_argument('--rate-hz', type=float, default=100.0)
    args = parser.parse_args(argv)
    if args.samples < 2 or not args.rate_hz > 0:
        parser.error('--samples must be >= 2 and --rate-hz > 0')
    try:
        return _run(args)
    except KneeseatError as err:
        print(f'tracker_demo: error: {err}', file=sys.stderr)
        return 1


if __name__ == '__main__':
    sys.exit(main())
