"""An rmw_zenoh subscriber that is not the formation's code: Python
eclipse-zenoh and rosbags' CDR decoder. Subscribes one topic on the key
rmw_zenoh uses (the type hash from rosbags' own REP 2011 computation),
checks every sample's 33-byte attachment, lists the ROS 2 liveliness tokens,
and writes what it saw as JSON.

    python listen.py --connect tcp/127.0.0.1:7447 --topic /follower_1/odom \
        --type nav_msgs/msg/Odometry --seconds 20 --out seen.json
"""
import argparse
import json
import struct
import signal
import sys
import threading
import time

import zenoh
from rosbags.typesys import Stores, get_typestore


def data_key(domain, topic, typename, typehash):
    pkg, kind, name = typename.split("/")
    return f"{domain}/{topic.strip('/')}/{pkg}::{kind}::dds_::{name}_/{typehash}"


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--connect", required=True)
    ap.add_argument("--domain", type=int, default=0)
    ap.add_argument("--topic", required=True)
    ap.add_argument("--type", required=True)
    ap.add_argument("--seconds", type=float, default=30.0, help="at most this long (SIGTERM ends it earlier)")
    ap.add_argument("--quiet-after", type=float, default=3.0, help="stop once samples stop for this long")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()

    store = get_typestore(Stores.ROS2_JAZZY)
    typehash = store.hash_rihs01(a.type)
    key = data_key(a.domain, a.topic, a.type, typehash)

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([a.connect]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)

    samples = []
    lock = threading.Lock()
    last = [None]

    def on_sample(sample):
        att = sample.attachment
        att = att.to_bytes() if att is not None else b""
        rec = {"key": str(sample.key_expr), "attachment_len": len(att)}
        if len(att) == 33 and att[16] == 0x10:
            seq, ts = struct.unpack("<qq", att[:16])
            rec.update(seq=seq, source_ns=ts, gid=att[17:].hex())
        try:
            m = store.deserialize_cdr(sample.payload.to_bytes(), a.type)
            rec["decoded"] = True
            if a.type == "nav_msgs/msg/Odometry":
                p, q, t = m.pose.pose.position, m.pose.pose.orientation, m.twist.twist
                rec.update(
                    stamp_ns=m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec,
                    frame_id=m.header.frame_id, child_frame_id=m.child_frame_id,
                    x=p.x, y=p.y, qz=q.z, qw=q.w, v=t.linear.x, w=t.angular.z,
                )
        except Exception as e:  # noqa: BLE001 - every failure is the finding
            rec["decoded"] = False
            rec["error"] = str(e)
        with lock:
            samples.append(rec)
            last[0] = time.monotonic()

    sub = session.declare_subscriber(key, on_sample)
    print(f"listening on {key}", file=sys.stderr, flush=True)
    tokens = set()
    began = time.monotonic()
    # Until SIGTERM (the test's, once the run it listens to is over), or --seconds.
    ended = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: ended.set())
    while time.monotonic() - began < a.seconds and not ended.is_set():
        ended.wait(0.5)
        for reply in session.liveliness().get(f"@ros2_lv/{a.domain}/**", timeout=2.0):
            if reply.ok is not None:
                tokens.add(str(reply.ok.key_expr))
        with lock:
            if last[0] is not None and time.monotonic() - last[0] > a.quiet_after:
                break
    sub.undeclare()
    session.close()
    with open(a.out, "w") as f:
        json.dump({"key": key, "samples": samples, "tokens": sorted(tokens)}, f)
    print(f"{len(samples)} samples, {len(tokens)} tokens", file=sys.stderr)


if __name__ == "__main__":
    main()
