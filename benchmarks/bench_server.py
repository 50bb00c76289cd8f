#!/usr/bin/env python3
"""End-to-end benchmark of the table_server node over Fast DDS on this machine.

Three processes: the node (the venv's `table_server` console script), a tracker that
publishes geometry_msgs/PoseStamped on /knee/pose (0.5 s unmeasured warm-up, then
--rate-hz for --rate-s seconds, then as fast as it can for --flat-s seconds), and this
process, which receives every /knee/<body>/pose answer and measures latency = receive
time - input stamp (both from the system clock: the tracker stamps with time.time_ns(),
the node's ROS clock is the system clock). Node CPU % comes from /proc/<pid>/stat over
each phase. One interpolation and one
attitude decode are timed in-process as well.

    python benchmarks/bench_server.py                 # 30 s at 1 kHz + 10 s flat out
    python benchmarks/bench_server.py --rate-s 5 --flat-s 2
    python benchmarks/bench_server.py --rate-hz 2000 --rate-s 30 --flat-s 0
    python benchmarks/bench_server.py --rate-s 60 --flat-s 0 --competitor
    python benchmarks/bench_server.py --rate-hz 2000 --rate-s 30 --flat-s 0 --fifo 10

Targets: 1 kHz with zero drops and p99 <= 2 ms end-to-end; one interpolation <= 20 us;
2 kHz, 100% answered, p99 <= 1 ms; 1 kHz beside a CPU-bound process, 100% answered.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
from pathlib import Path
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
from typing import Any

import numpy as np
from machine import call_times_us, cpu_seconds, describe_machine

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'test'))   # conftest: synthetic_table, ros_env

BODIES = ('tibia', 'patella')
WARMUP_S = 0.5     # the tracker's unmeasured lead-in (s)


def tracker(domain_id: int, rate_hz: float, rate_s: float, flat_s: float) -> int:
    """The publisher process: prints one JSON line per phase on stdout."""
    import rclpy
    from rclpy.qos import QoSProfile, QoSReliabilityPolicy

    from conftest import synthetic_table
    from kneeseat_core.geometry import quat_from_matrix
    from kneeseat_ros.conversions import pose_stamped, stamp_from_ns

    from geometry_msgs.msg import PoseStamped
    rclpy.init(domain_id=domain_id)
    node = rclpy.create_node('bench_tracker')
    pub = node.create_publisher(PoseStamped, '/knee/pose',
                                QoSProfile(depth=100, reliability=QoSReliabilityPolicy.RELIABLE))
    axes = synthetic_table().axes
    t = np.linspace(0.0, 2.0, 2000, endpoint=False)          # a 2 s knee cycle, 1 ms apart
    quats = quat_from_matrix(axes.orientation(-0.8 + 0.7 * np.sin(np.pi * t),
                                              0.05 * np.sin(2 * np.pi * t),
                                              0.1 * np.sin(np.pi * t)))
    msgs = [pose_stamped((0.0, 0.0, 0.0), q, stamp_from_ns(0), 'femur') for q in quats]
    deadline = time.monotonic() + 30.0
    while pub.get_subscription_count() == 0:
        if time.monotonic() > deadline:
            print(json.dumps({'error': 'node not discovered'}), flush=True)
            return 1
        rclpy.spin_once(node, timeout_sec=0.05)
    print(json.dumps({'ready': True}), flush=True)
    # warm-up, not measured: right after discovery a sample can reach a reader whose side
    # of the match is not complete yet and be dropped; these stamps precede the phases
    period_ns = int(1e9 / rate_hz)
    now = due = time.monotonic_ns()
    end = now + int(WARMUP_S * 1e9)
    while now < end:
        if now < due:
            time.sleep((due - now) * 1e-9)
        due += period_ns
        msg = msgs[0]
        msg.header.stamp = stamp_from_ns(time.time_ns())
        pub.publish(msg)
        now = time.monotonic_ns()
    phases = [(f'{rate_hz:g} Hz', rate_s, period_ns)]
    if flat_s > 0:
        phases.append(('flat out', flat_s, 0))
    for phase, duration, period_ns in phases:
        start = time.monotonic_ns()
        end = start + int(duration * 1e9)
        start_ns, sent, due = time.time_ns(), 0, start
        while True:
            now = time.monotonic_ns()
            if now >= end:
                break
            if period_ns:
                if now < due:
                    time.sleep((due - now) * 1e-9)
                due += period_ns
            msg = msgs[sent % len(msgs)]
            msg.header.stamp = stamp_from_ns(time.time_ns())
            pub.publish(msg)
            sent += 1
        print(json.dumps({'phase': phase, 'start_ns': start_ns, 'end_ns': time.time_ns(),
                          'sent': sent}), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def percentiles_ms(lat_ns: np.ndarray) -> str:
    if lat_ns.size == 0:
        return 'no answers'
    ms = lat_ns * 1e-6
    return (f'p50 {np.percentile(ms, 50):.3f} ms, p99 {np.percentile(ms, 99):.3f} ms, '
            f'max {ms.max():.3f} ms')


def time_calls(fn: Any, n: int = 20000, runs: int = 5) -> tuple[float, float]:
    """Median and best-run per-call time (us) of fn()."""
    per = call_times_us(fn, n, runs)
    return float(np.median(per)), float(min(per))


def _end_process(proc: subprocess.Popen[Any] | None) -> None:
    """Terminate `proc` if it still runs (kill it after 5 s) and wait for it."""
    if proc is None or proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--rate-hz', type=float, default=1000.0)
    parser.add_argument('--rate-s', type=float, default=30.0)
    parser.add_argument('--flat-s', type=float, default=10.0)
    parser.add_argument('--domain-id', type=int, default=0, help='0 = derive from pid')
    parser.add_argument('--competitor', action='store_true',
                        help='run a CPU-bound process (a Python busy loop) meanwhile')
    parser.add_argument('--fifo', type=int, default=0, metavar='PRIO',
                        help='run the tracker, the node and the receiver with SCHED_FIFO '
                             'priority PRIO (the competitor stays SCHED_OTHER); 0 = off')
    parser.add_argument('--tracker', action='store_true', help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    from conftest import next_domain_id, ros_env, synthetic_table
    domain_id = args.domain_id or next_domain_id()
    os.environ.update(ros_env(domain_id))
    if args.tracker:
        return tracker(domain_id, args.rate_hz, args.rate_s, args.flat_s)
    if args.fifo:       # inherited by the node and the tracker started below
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.fifo))

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, QoSReliabilityPolicy

    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped
    from kneeseat_core.table import read_table, write_table
    from kneeseat_ros.conversions import AttitudeDecoder, angles_from_pose_stamped
    from kneeseat_ros.conversions import pose_stamped_for_attitude, stamp_from_ns

    print(describe_machine())
    print(f'ROS_DOMAIN_ID {domain_id}, RMW {os.environ.get("RMW_IMPLEMENTATION", "default")}; '
          + (f'tracker, node and receiver at SCHED_FIFO {args.fifo}' if args.fifo
             else 'default scheduling (SCHED_OTHER)'))
    tmp = Path(tempfile.mkdtemp(prefix='bench_server_'))
    table_path = tmp / 'knee.npz'
    write_table(table_path, synthetic_table(flexion_deg=(-90.0, 0.0, 91),
                                            varus_deg=(-10.0, 10.0, 21)))
    table = read_table(table_path)
    rng = np.random.default_rng(0)
    queries = [tuple(q) for q in rng.uniform(np.radians([-90, -10]), np.radians([0, 10]),
                                             (1000, 2))]
    it = iter(range(10 ** 9))
    med, best = time_calls(lambda: table.interpolate(*queries[next(it) % 1000]))
    print(f'interpolate (91 x 21 x 2 bodies): median {med:.2f} us, best run {best:.2f} us '
          'per call (target <= 20 us)')
    decoder = AttitudeDecoder(table.axes)
    msg = pose_stamped_for_attitude(table.axes, -0.5, 0.05, stamp_from_ns(1), 'femur', 0.1)
    med, best = time_calls(lambda: angles_from_pose_stamped(msg, decoder, 'femur'))
    print(f'PoseStamped -> (flexion, varus) validate + decode: median {med:.2f} us')

    node_proc = subprocess.Popen(
        [str(Path(sys.prefix) / 'bin' / 'table_server'), '--ros-args', '-p',
         f'table:={table_path}', '--log-level', 'warn'], stdout=subprocess.DEVNULL,
        stderr=open(tmp / 'node.err', 'wb'), env=dict(os.environ))
    stop = threading.Event()
    spinner: threading.Thread | None = None
    hog: subprocess.Popen[bytes] | None = None
    trk: subprocess.Popen[str] | None = None
    try:
        rclpy.init(domain_id=domain_id)
        rx = rclpy.create_node('bench_receiver')
        got: dict[str, list[tuple[int, int]]] = {b: [] for b in BODIES}
        # The receiver must be cheaper than the node or it measures itself: raw CDR (the stamp
        # is the first field after the 4-byte encapsulation header) and drain the queue per wake.
        subs = {}
        for body in BODIES:
            def on_raw(data: bytes, lst: list[tuple[int, int]] = got[body],
                       body: str = body) -> None:
                sub = subs[body]
                while data is not None:
                    sec, nanosec = struct.unpack_from('<iI', data, 4)
                    lst.append((sec * 1_000_000_000 + nanosec, time.time_ns()))
                    with sub.handle:
                        taken = sub.handle.take_message(sub.msg_type, True)
                    data = taken[0] if taken is not None else None

            subs[body] = rx.create_subscription(
                PoseStamped, f'/knee/{body}/pose', on_raw,
                QoSProfile(depth=1000, reliability=QoSReliabilityPolicy.RELIABLE), raw=True)
        status: dict[str, str] = {}

        def on_diag(m: DiagnosticArray) -> None:
            for s in m.status:
                if s.name == 'kneeseat table_server':
                    status.clear()
                    status.update({kv.key: kv.value for kv in s.values})

        rx.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 10)
        executor = SingleThreadedExecutor()
        executor.add_node(rx)
        deadline = time.monotonic() + 30.0
        while not all(rx.count_publishers(f'/knee/{b}/pose') for b in BODIES):
            if time.monotonic() > deadline or node_proc.poll() is not None:
                print('table_server did not come up:', (tmp / 'node.err').read_text())
                return 1
            executor.spin_once(timeout_sec=0.05)

        def spin() -> None:
            # like table_server.serve(): wait on the output topics directly (rclpy's executor
            # rebuilds its wait set per message, and at 2000 answers/s the receiver would
            # compete with the node for the 2 cores); the executor serves /diagnostics
            from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
            wait_set = _rclpy.WaitSet(len(BODIES), 0, 0, 0, 0, 0, rx.context.handle)
            due = 0.0
            while not stop.is_set():
                now = time.monotonic()
                if now >= due:
                    executor.spin_once(timeout_sec=0.0)
                    due = now + 0.05
                with contextlib.ExitStack() as held:
                    held.enter_context(rx.context.handle)
                    wait_set.clear_entities()
                    for sub in subs.values():
                        held.enter_context(sub.handle)
                        wait_set.add_subscription(sub.handle)
                    wait_set.wait(int(max(due - time.monotonic(), 0.0) * 1e9))
                for body, sub in subs.items():
                    while True:
                        with sub.handle:
                            taken = sub.handle.take_message(sub.msg_type, True)
                        if taken is None:
                            break
                        sec, nanosec = struct.unpack_from('<iI', taken[0], 4)
                        got[body].append((sec * 1_000_000_000 + nanosec, time.time_ns()))

        spinner = threading.Thread(target=spin)
        spinner.start()

        if args.competitor:
            hog = subprocess.Popen([sys.executable, '-c', 'while True: pass'], preexec_fn=lambda:
                                   os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0)))
            print(f'competitor: a CPU-bound busy loop, pid {hog.pid}')
        trk = subprocess.Popen([sys.executable, __file__, '--tracker', '--domain-id',
                                str(domain_id), '--rate-hz', str(args.rate_hz), '--rate-s',
                                str(args.rate_s), '--flat-s', str(args.flat_s)],
                               stdout=subprocess.PIPE, text=True, env=dict(os.environ))
        phases, cpu = [], []
        assert trk.stdout is not None
        for line in trk.stdout:
            cpu.append((time.monotonic(), cpu_seconds(node_proc.pid)))
            record = json.loads(line)
            if 'ready' not in record:
                phases.append(record)
        trk.wait()
        hog_cpu = None
        if hog is not None:
            hog_cpu = cpu_seconds(hog.pid)
            hog.kill()
            hog.wait()
        # let the last answers arrive: wait until nothing new for 0.5 s (bounded)
        counts, quiet_since = -1, time.monotonic()
        while time.monotonic() - quiet_since < 0.5:
            n = sum(len(v) for v in got.values())
            if n != counts:
                counts, quiet_since = n, time.monotonic()
            time.sleep(0.05)          # a pause in a benchmark loop, not test synchronisation
        diag = dict(status)
        stop.set()
        spinner.join()
        node_proc.send_signal(signal.SIGTERM)
        rc = node_proc.wait(timeout=15)
    finally:    # an early return or an error must not leave a process or the spinner running
        stop.set()
        if spinner is not None:
            spinner.join()
        for proc in (trk, hog, node_proc):
            _end_process(proc)

    from kneeseat_ros.table_server import INPUT_QOS, OUTPUT_QOS
    print('tracker: reliable PoseStamped publisher, separate process; node input QoS best '
          f'effort depth {INPUT_QOS.depth}; outputs reliable depth {OUTPUT_QOS.depth}; '
          'receiver reliable depth 1000, raw')
    stamps = {b: np.array(got[b], dtype=np.int64).reshape(-1, 2) for b in BODIES}
    for i, ph in enumerate(phases):
        if 'error' in ph:
            print('tracker error:', ph['error'])
            return 1
        wall = (ph['end_ns'] - ph['start_ns']) * 1e-9
        t0, c0 = cpu[i]
        t1, c1 = cpu[i + 1]
        lat, answered = [], []
        for b in BODIES:
            s = stamps[b]
            sel = s[(s[:, 0] >= ph['start_ns']) & (s[:, 0] <= ph['end_ns'])]
            answered.append(len(np.unique(sel[:, 0])))
            lat.append(sel[:, 1] - sel[:, 0])
        lat_all = np.concatenate(lat)
        print(f'[{ph["phase"]}] {wall:.1f} s: sent {ph["sent"]} ({ph["sent"] / wall:.0f}/s), '
              f'answered {min(answered)} (per body {answered}), lost '
              f'{ph["sent"] - min(answered)}; latency stamp -> received: '
              f'{percentiles_ms(lat_all)}; node CPU {100 * (c1 - c0) / (t1 - t0):.0f} %')
    keys = ('received', 'answered', 'dropped', 'clamped', 'latency_p50_ms', 'latency_p99_ms',
            'latency_max_ms', 'rate_hz')
    print('node diagnostics (last, window = last period): '
          + ', '.join(f'{k} {diag.get(k)}' for k in keys))
    print(f'table_server exit code after SIGTERM: {rc}')
    if hog_cpu is not None:
        print(f'competitor CPU time: {hog_cpu:.1f} s')
    print(f'load average after: {os.getloadavg()[0]:.2f}')
    executor.shutdown()
    rx.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
