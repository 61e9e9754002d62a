"""A robot that is not the formation's code: a unicycle integrated from
`cmd_vel`, publishing `odom` on rmw_zenoh's wire (Python eclipse-zenoh and
rosbags' CDR, with the 33-byte attachment and liveliness tokens). After
--stop-after seconds of driving it stops publishing odometry but keeps
listening, and counts the commands it still receives (an agent should send
zero velocity). It drives until SIGTERM (or --seconds, a guard), so that a
slow start of the formation never outlasts it; --out then holds its last
pose and every pose it published.

    python unicycle.py --connect tcp/127.0.0.1:7447 --id 1 --pose 0 0 0 \
        --dt 0.01 --seconds 20 --stop-after 8 --out robot.json
"""
import argparse
import json
import math
import signal
import sys
import threading
import time

import numpy as np

import rmw


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--connect", required=True)
    ap.add_argument("--domain", type=int, default=0)
    ap.add_argument("--id", type=int, required=True)
    ap.add_argument("--namespace", default=None, help="its topics' namespace (default follower_<id>; `leader` for a leader robot)")
    ap.add_argument("--pose", type=float, nargs=3, default=[0.0, 0.0, 0.0])
    ap.add_argument("--dt", type=float, default=0.01)
    ap.add_argument("--seconds", type=float, default=20.0, help="at most this long (SIGTERM ends it earlier)")
    ap.add_argument("--stop-after", type=float, default=1e9, help="s after the first command")
    ap.add_argument("--frame", default=None, help="odometry frame_id (default follower_<id>/odom)")
    ap.add_argument("--wrong-frame-every", type=int, default=0,
                    help="publish every Nth odometry message in frame `map` (to be refused)")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()

    store = rmw.STORE
    T = store.types
    ns = a.namespace or f"follower_{a.id}"

    def key(topic, typename):
        return rmw.key(a.domain, f"{ns}/{topic}", typename)

    session = rmw.session(a.connect)
    odom_t, twist_t = "nav_msgs/msg/Odometry", "geometry_msgs/msg/Twist"
    node = rmw.Node(session, a.domain, ns, "unicycle")
    gid = rmw.gid(node.endpoint(1, "MP", f"{ns}/odom", odom_t))
    node.endpoint(2, "MS", f"{ns}/cmd_vel", twist_t)
    pub = session.declare_publisher(key("odom", odom_t))

    lock = threading.Lock()
    state = {"cmd": (0.0, 0.0), "first": None, "after_stop": [], "commands": 0}

    def on_cmd(sample):
        m = store.deserialize_cdr(sample.payload.to_bytes(), twist_t)
        with lock:
            state["cmd"] = (m.linear.x, m.angular.z)
            state["commands"] += 1
            if state["first"] is None:
                state["first"] = time.monotonic()
            elif time.monotonic() - state["first"] > a.stop_after:
                state["after_stop"].append([m.linear.x, m.angular.z])

    sub = session.declare_subscriber(key("cmd_vel", twist_t), on_cmd)
    ended = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: ended.set())
    trail = []
    x, y, th = a.pose
    v = w = 0.0
    seq = 1
    began = time.monotonic()
    published = 0
    tick = began
    while time.monotonic() - began < a.seconds and not ended.is_set():
        tick += a.dt
        ended.wait(max(0.0, tick - time.monotonic()))
        with lock:
            v, w = state["cmd"]
            first = state["first"]
        stopped = first is not None and time.monotonic() - first > a.stop_after
        if stopped:
            continue
        x += a.dt * v * math.cos(th)
        y += a.dt * v * math.sin(th)
        th += a.dt * w
        now = time.time_ns()
        stamp = T["builtin_interfaces/msg/Time"](sec=now // 1_000_000_000, nanosec=now % 1_000_000_000)
        frame = a.frame or f"{ns}/odom"
        if a.wrong_frame_every and (published + 1) % a.wrong_frame_every == 0:
            frame = "map"
        header = T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)
        P, Q, V3 = T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"], T["geometry_msgs/msg/Vector3"]
        pose = T["geometry_msgs/msg/Pose"](position=P(x=x, y=y, z=0.0),
                                           orientation=Q(x=0.0, y=0.0, z=math.sin(th / 2), w=math.cos(th / 2)))
        twist = T["geometry_msgs/msg/Twist"](linear=V3(x=v, y=0.0, z=0.0), angular=V3(x=0.0, y=0.0, z=w))
        msg = T[odom_t](
            header=header, child_frame_id=f"{ns}/base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)),
        )
        att = rmw.attachment(seq, now, gid)
        pub.put(bytes(store.serialize_cdr(msg, odom_t)), attachment=att)
        trail.append([x, y, th])
        seq += 1
        published += 1
        if first is None and published == 1:
            print(f"unicycle {a.id}: publishing odometry", file=sys.stderr, flush=True)
    sub.undeclare()
    node.close()
    session.close()
    with lock:
        out = {"published": published, "commands": state["commands"], "after_stop": state["after_stop"],
               "pose": [x, y, th], "published_poses": trail}
    with open(a.out, "w") as f:
        json.dump(out, f)
    print(f"unicycle {a.id}: {published} odometry messages, {out['commands']} commands, "
          f"{len(out['after_stop'])} after it stopped", file=sys.stderr)


if __name__ == "__main__":
    main()
