"""A /tf subscriber in its own process (run with the tf2_msgs build's environment).

    python tf_probe.py SPEC.json     (ROS_DOMAIN_ID etc. from the environment)

SPEC: {"pairs": [{"stamp": ns, "femur": [px, py, pz, qx, qy, qz, qw], "tibia": [...]}, ...]}
It publishes each pair of marker-cluster poses (frame 'world') on tracker/femur/pose and
tracker/tibia/pose, waits for the /tf message carrying that stamp, and prints one JSON
object: the TFMessage type hash the graph reports for the node's /tf publisher, and per
stamp the received transforms [parent, child, px, py, pz, qx, qy, qz, qw]. Warm-up pairs
(the first pose, earlier stamps) are sent until one is answered, since discovery may eat
the first best-effort samples. Exits 1 with a message on stderr after 30 s without answer.
"""
from __future__ import annotations

import json
import sys
import time
from typing import Any

from geometry_msgs.msg import PoseStamped
import rclpy
from rclpy.qos import QoSProfile, QoSReliabilityPolicy
from tf2_msgs.msg import TFMessage


def pose(values: list[float], stamp: int) -> PoseStamped:
    msg = PoseStamped()
    msg.header.frame_id = 'world'
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 10**9)
    p, o = msg.pose.position, msg.pose.orientation
    p.x, p.y, p.z, o.x, o.y, o.z, o.w = values
    return msg


def main() -> int:
    spec = json.loads(open(sys.argv[1]).read())
    rclpy.init()
    node = rclpy.create_node('tf_probe')
    qos = QoSProfile(depth=100, reliability=QoSReliabilityPolicy.RELIABLE)
    pubs = [node.create_publisher(PoseStamped, f'tracker/{s}/pose', qos)
            for s in ('femur', 'tibia')]
    got: dict[int, list[Any]] = {}

    def on_tf(msg: TFMessage) -> None:
        for t in msg.transforms:
            s = t.header.stamp.sec * 10**9 + t.header.stamp.nanosec
            tr, r = t.transform.translation, t.transform.rotation
            got.setdefault(s, []).append([t.header.frame_id, t.child_frame_id, tr.x, tr.y,
                                          tr.z, r.x, r.y, r.z, r.w])

    node.create_subscription(TFMessage, '/tf', on_tf, qos)

    def spin_until(done: Any, what: str, every: Any = None) -> None:
        deadline = time.monotonic() + 30.0
        while not done():
            if time.monotonic() > deadline:
                print(f'tf_probe: {what} not within 30 s', file=sys.stderr)
                sys.exit(1)
            if every is not None:
                every()
            rclpy.spin_once(node, timeout_sec=0.02)

    spin_until(lambda: all(p.get_subscription_count() for p in pubs)
               and node.count_publishers('/tf') > 0, 'discovery')
    first, warm = spec['pairs'][0], [spec['pairs'][0]['stamp'] - 10**9, -1.0]

    def send_warm() -> None:
        if time.monotonic() - warm[1] > 0.3:
            warm[0], warm[1] = warm[0] + 10**6, time.monotonic()
            for pub, side in zip(pubs, ('femur', 'tibia')):
                pub.publish(pose(first[side], warm[0]))

    spin_until(lambda: bool(got), 'a warm-up answer', send_warm)
    got.clear()
    for pair in spec['pairs']:
        for pub, side in zip(pubs, ('femur', 'tibia')):
            pub.publish(pose(pair[side], pair['stamp']))
        spin_until(lambda s=pair['stamp']: s in got, f'/tf for stamp {pair["stamp"]}')
    info = node.get_publishers_info_by_topic('/tf')
    print(json.dumps({'hash': [str(i.topic_type_hash) for i in info],
                      'types': [i.topic_type for i in info],
                      'transforms': {str(k): v for k, v in got.items()}}))
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
