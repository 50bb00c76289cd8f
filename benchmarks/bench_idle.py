#!/usr/bin/env python3
"""Idle cost of the table_server node against a plain rclpy node with the same inputs.

Nobody publishes: both processes sit on their own ROS domain and the CPU time they take
(utime + stime from /proc/<pid>/stat) over --seconds is measured, --runs times each,
alternating. The plain node subscribes to knee/pose and knee/joint_states with the node's
QoS, has a 1 Hz timer like the node's /diagnostics and runs `rclpy.spin`. A last run starts
the node with `--log-level debug` and counts the lines it prints per second while idle.

    python benchmarks/bench_idle.py [--seconds 20] [--runs 3]
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path
import signal
import statistics
import subprocess
import sys
import tempfile
import time

from machine import cpu_seconds, describe_machine

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'test'))   # conftest: synthetic tables, ros_env

PLAIN = """
import rclpy
from geometry_msgs.msg import PoseStamped
from sensor_msgs.msg import JointState
from kneeseat_ros.table_server import INPUT_QOS
rclpy.init()
node = rclpy.create_node('plain')
node.create_subscription(PoseStamped, 'knee/pose', lambda m: None, INPUT_QOS)
node.create_subscription(JointState, 'knee/joint_states', lambda m: None, INPUT_QOS)
node.create_timer(1.0, lambda: None)
print('ready', flush=True)
try:
    rclpy.spin(node)
except KeyboardInterrupt:
    pass
"""


def measure(args: list[str], env: dict[str, str], seconds: float, settle_s: float,
            log: Path) -> tuple[float, int]:
    """CPU % of one core over `seconds` after `settle_s`, and lines printed meanwhile."""
    with open(log, 'wb') as out:
        proc = subprocess.Popen(args, stdout=out, stderr=subprocess.STDOUT, env=env)
    try:
        time.sleep(settle_s)             # start-up (imports, discovery) is not idle time
        c0, t0, n0 = cpu_seconds(proc.pid), time.monotonic(), len(log.read_bytes().splitlines())
        time.sleep(seconds)              # a measurement window, not synchronisation
        c1, t1, n1 = cpu_seconds(proc.pid), time.monotonic(), len(log.read_bytes().splitlines())
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            raise
    return 100.0 * (c1 - c0) / (t1 - t0), int(round((n1 - n0) / (t1 - t0)))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--seconds', type=float, default=20.0)
    parser.add_argument('--runs', type=int, default=3)
    parser.add_argument('--settle-s', type=float, default=3.0)
    args = parser.parse_args(argv)
    from conftest import next_domain_id, ros_env, write_synthetic_table
    env = ros_env(next_domain_id())
    print(describe_machine())
    tmp = Path(tempfile.mkdtemp(prefix='bench_idle_'))
    table = write_synthetic_table(tmp / 'knee.npz')
    node = [str(Path(sys.prefix) / 'bin' / 'table_server'), '--ros-args', '-p',
            f'table:={table}']
    plain = [sys.executable, '-c', PLAIN]
    cpu: dict[str, list[float]] = {'table_server': [], 'plain rclpy node': []}
    for run in range(args.runs):
        for name, cmd in (('table_server', node), ('plain rclpy node', plain)):
            pct, _ = measure(cmd, env, args.seconds, args.settle_s, tmp / 'log')
            cpu[name].append(pct)
            print(f'run {run + 1}: {name}: {pct:.2f} % of a core over {args.seconds:g} s',
                  flush=True)
    for name, values in cpu.items():
        print(f'{name}: idle CPU median {statistics.median(values):.2f} % of a core '
              f'({", ".join(f"{v:.2f}" for v in values)})')
    _, lines = measure([*node, '--log-level', 'debug'], env, args.seconds, args.settle_s,
                       tmp / 'debug.log')
    print(f'table_server --log-level debug, idle: {lines} lines/s')
    print(f'load average after: {os.getloadavg()[0]:.2f}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
