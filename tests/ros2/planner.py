"""A planner that is not the formation's code: nav_msgs/Path on
`/leader/path` over rmw_zenoh's wire (Python eclipse-zenoh and rosbags'
CDR, with the 33-byte attachment and liveliness tokens), as Nav2 publishes
its plan. It waits until the topic --wait-for (e.g. follower_1/odom)
carries a message, then publishes each --route (points `x,y;x,y;…`, in
frame --frame) --repeat times, --every seconds apart, in order.

    python planner.py --connect tcp/127.0.0.1:7447 --wait-for follower_1/odom \
        --route "1,0;1,1" --route "9,0" --repeat 2 --every 1 --out planner.json
"""
import argparse
import json
import math
import sys
import time

import rmw


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--connect", required=True)
    ap.add_argument("--domain", type=int, default=0)
    ap.add_argument("--wait-for", required=True)
    ap.add_argument("--wait-type", default="nav_msgs/msg/Odometry")
    ap.add_argument("--route", action="append", required=True, help="x,y;x,y;… (repeatable)")
    ap.add_argument("--frame", default="world")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--every", type=float, default=1.0)
    ap.add_argument("--give-up", type=float, default=120.0)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    routes = [[tuple(float(v) for v in p.split(",")) for p in r.split(";")] for r in a.route]

    T = rmw.STORE.types
    path_t = "nav_msgs/msg/Path"
    session = rmw.session(a.connect)
    node = rmw.Node(session, a.domain, "planner", "planner")
    gid = rmw.gid(node.endpoint(1, "MP", "leader/path", path_t))
    pub = session.declare_publisher(rmw.key(a.domain, "leader/path", path_t))
    rmw.wait_for(session, a.domain, a.wait_for, a.wait_type, a.give_up, "planner")
    P, Q = T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"]
    sent, seq = [], 1
    for route in routes:
        for _ in range(a.repeat):
            now = time.time_ns()
            stamp = T["builtin_interfaces/msg/Time"](sec=now // 1_000_000_000, nanosec=now % 1_000_000_000)
            header = T["std_msgs/msg/Header"](stamp=stamp, frame_id=a.frame)
            poses = []
            for i, (x, y) in enumerate(route):
                nx, ny = route[min(i + 1, len(route) - 1)]
                yaw = math.atan2(ny - y, nx - x)
                pose = T["geometry_msgs/msg/Pose"](position=P(x=x, y=y, z=0.0),
                                                   orientation=Q(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)))
                poses.append(T["geometry_msgs/msg/PoseStamped"](header=header, pose=pose))
            msg = T[path_t](header=header, poses=poses)
            pub.put(bytes(rmw.STORE.serialize_cdr(msg, path_t)), attachment=rmw.attachment(seq, now, gid))
            sent.append({"ns": now, "route": route})
            seq += 1
            time.sleep(a.every)
    node.close()
    session.close()
    with open(a.out, "w") as f:
        json.dump({"sent": sent}, f)
    print(f"planner: {len(sent)} routes sent", file=sys.stderr)


if __name__ == "__main__":
    main()
