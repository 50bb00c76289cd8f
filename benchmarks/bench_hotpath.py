#!/usr/bin/env python3
"""Where one message's time goes in table_server, per stage, message objects vs CDR bytes.

One JointState in, two PoseStamped out (the synthetic 91 x 21 table), in this process over
real rclpy/Fast DDS: a publisher fills the node-side subscription, a subscription in this
process is matched to the two outputs (so publish does the real DDS write). Each stage is
timed over --n messages, --runs times; the medians of the runs are printed in us per
message. "objects" is the path before the CDR hot path (rclpy deserialises into a message, the
fields are read from it, two PoseStamped objects are built and published, the recorder
serialises them with cdr.serialize); "cdr" is the node's path now (raw take,
kneeseat_ros.cdr read and write, publish bytes, record the same bytes).

    python benchmarks/bench_hotpath.py [--n 5000] [--runs 5]
"""
from __future__ import annotations

import argparse
import os
from pathlib import Path
import statistics
import sys
import tempfile
import time
from typing import Any, Callable

from machine import call_times_us, describe_machine

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / 'test'))   # conftest: synthetic tables, ros_env


def per_call_us(fn: Callable[[], Any], n: int, runs: int) -> float:
    """Median over `runs` of the mean time of `fn()` over `n` calls (us)."""
    return statistics.median(call_times_us(fn, n, runs))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--n', type=int, default=5000)
    parser.add_argument('--runs', type=int, default=5)
    args = parser.parse_args(argv)
    from conftest import next_domain_id, ros_env, synthetic_table
    os.environ.update(ros_env(next_domain_id()))
    import rclpy
    from rclpy.qos import QoSProfile, QoSReliabilityPolicy
    from rclpy.serialization import serialize_message

    from geometry_msgs.msg import PoseStamped
    from kneeseat_core.table import read_table, write_table
    from kneeseat_ros.cdr import (decode_joint_state, encode_joint_state, PoseStampedWriter,
                                  serialize)
    from kneeseat_ros.conversions import (angles_from_joint_state, angles_from_joints, joint_state,
                                          pose_stamped, stamp_from_ns)
    from kneeseat_ros.bag.recorder import BagRecorder
    from kneeseat_ros.table_server import INPUT_QOS, OUTPUT_QOS
    from sensor_msgs.msg import JointState

    print(describe_machine())
    tmp = Path(tempfile.mkdtemp(prefix='bench_hotpath_'))
    write_table(tmp / 'knee.npz', synthetic_table(flexion_deg=(-90.0, 0.0, 91),
                                                  varus_deg=(-10.0, 10.0, 21)))
    table = read_table(tmp / 'knee.npz')
    rclpy.init()
    node = rclpy.create_node('bench_hotpath')
    reliable = QoSProfile(depth=100, reliability=QoSReliabilityPolicy.RELIABLE)
    pub_in = node.create_publisher(JointState, 'knee/joint_states', reliable)
    subs = {raw: node.create_subscription(JointState, 'knee/joint_states', lambda m: None,
                                          QoSProfile(depth=args.n + 10,
                                                     reliability=INPUT_QOS.reliability),
                                          raw=raw) for raw in (False, True)}
    outs = [node.create_publisher(PoseStamped, f'knee/{b}/pose', OUTPUT_QOS)
            for b in ('tibia', 'patella')]
    for b in ('tibia', 'patella'):
        node.create_subscription(PoseStamped, f'knee/{b}/pose', lambda m: None, OUTPUT_QOS)
    deadline = time.monotonic() + 10
    while pub_in.get_subscription_count() < 2 or any(
            p.get_subscription_count() < 1 for p in outs):
        if time.monotonic() > deadline:
            print('discovery failed')
            return 1
        rclpy.spin_once(node, timeout_sec=0.05)
    msg = joint_state(-0.5, 0.03, stamp_from_ns(1_700_000_000_123_456_789))
    data = serialize_message(msg)
    n, runs = args.n, args.runs
    stages: dict[str, dict[str, float]] = {}

    def take(raw: bool) -> float:
        sub = subs[raw]
        times = []
        for _ in range(runs):
            for _ in range(n):
                pub_in.publish(msg)
            got, t0 = 0, time.perf_counter()
            while got < n:
                with sub.handle:
                    if sub.handle.take_message(sub.msg_type, raw) is None:
                        break
                got += 1
            times.append((time.perf_counter() - t0) / max(got, 1) * 1e6)
            while True:                    # empty the other subscription's queue
                other = subs[not raw]
                with other.handle:
                    if other.handle.take_message(other.msg_type, not raw) is None:
                        break
        return statistics.median(times)

    stages['take'] = {'objects': take(False), 'cdr': take(True)}
    stages['decode + validate'] = {
        'objects': per_call_us(lambda: angles_from_joint_state(msg), n, runs),
        'cdr': per_call_us(lambda: (lambda f: angles_from_joints(f[3], f[4], len(f[5]),
                                                                 len(f[6])))(
            decode_joint_state(data)), n, runs)}
    stages['interpolate'] = {'objects': per_call_us(lambda: table.interpolate(-0.5, 0.03),
                                                    n, runs)}
    stages['interpolate']['cdr'] = stages['interpolate']['objects']
    look = table.interpolate(-0.5, 0.03)
    stamp = msg.header.stamp
    writer = PoseStampedWriter('femur')
    positions, orientations = look.position_m.tolist(), look.orientation_xyzw.tolist()
    poses = [(*p, *q) for p, q in zip(positions, orientations)]
    stages['build 2 PoseStamped'] = {
        'objects': per_call_us(lambda: [pose_stamped(look.position_m[i],
                                                     look.orientation_xyzw[i], stamp, 'femur')
                                        for i in range(2)], n, runs),
        'cdr': per_call_us(lambda: [writer.encode(stamp.sec, stamp.nanosec, (*p, *q))
                                    for p, q in zip(look.position_m.tolist(),
                                                    look.orientation_xyzw.tolist())], n, runs)}
    objs = [pose_stamped(look.position_m[i], look.orientation_xyzw[i], stamp, 'femur')
            for i in range(2)]
    raws = [writer.encode(stamp.sec, stamp.nanosec, p) for p in poses]
    stages['publish 2'] = {
        'objects': per_call_us(lambda: [p.publish(m) for p, m in zip(outs, objs)], n, runs),
        'cdr': per_call_us(lambda: [p.publish(m) for p, m in zip(outs, raws)], n, runs)}
    with BagRecorder(tmp / 'bag') as rec:
        for topic, kind in (('/knee/joint_states', 'sensor_msgs/msg/JointState'),
                            ('/knee/tibia/pose', 'geometry_msgs/msg/PoseStamped'),
                            ('/knee/patella/pose', 'geometry_msgs/msg/PoseStamped')):
            rec.add_topic(topic, kind)
        fields = decode_joint_state(data)

        def record_objects() -> None:
            rec.write('/knee/joint_states', msg, 1, 1)
            rec.write('/knee/tibia/pose', objs[0], 1, 1)
            rec.write('/knee/patella/pose', objs[1], 1, 1)

        def record_cdr() -> None:
            rec.write_raw('/knee/joint_states', encode_joint_state(*fields), 1, 1)
            rec.write_raw('/knee/tibia/pose', raws[0], 1, 1)
            rec.write_raw('/knee/patella/pose', raws[1], 1, 1)

        stages['record (when on)'] = {'objects': per_call_us(record_objects, n // 5, runs),
                                      'cdr': per_call_us(record_cdr, n // 5, runs)}
    assert serialize(objs[0]) == raws[0]
    print(f'per message (us, median of {runs} runs of {n}); JointState in, 2 PoseStamped out')
    print(f'{"stage":<24}{"objects":>10}{"cdr":>10}')
    total = {'objects': 0.0, 'cdr': 0.0}
    for name, row in stages.items():
        print(f'{name:<24}{row["objects"]:>10.1f}{row["cdr"]:>10.1f}')
        if not name.startswith('record'):
            for k in total:
                total[k] += row[k]
    print(f'{"total without record":<24}{total["objects"]:>10.1f}{total["cdr"]:>10.1f}')
    print(f'load average after: {os.getloadavg()[0]:.2f}')
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
