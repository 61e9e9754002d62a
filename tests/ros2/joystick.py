"""A joystick that is not the formation's code: geometry_msgs/Twist on
`/leader/cmd_vel` over rmw_zenoh's wire (Python eclipse-zenoh and rosbags'
CDR, with the 33-byte attachment and liveliness tokens), as `joy`'s teleop
node publishes it, at --rate Hz. It waits until the topic --wait-for
(e.g. follower_1/odom) carries a message, so that the script plays while
the run goes however long its start took; then it plays the --script
phases, each `seconds:v:w`, and falls silent (it sends no zero: the leader
must stop on its own time-out). --out gets what it sent.

    python joystick.py --connect tcp/127.0.0.1:7447 --wait-for follower_1/odom \
        --script 6:0.3:0 6:0.1:0.25 --rate 20 --out joystick.json
"""
import argparse
import json
import sys
import time

import rmw


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--connect", required=True)
    ap.add_argument("--domain", type=int, default=0)
    ap.add_argument("--wait-for", required=True, help="a topic (without the leading /) whose first message starts the script")
    ap.add_argument("--wait-type", default="nav_msgs/msg/Odometry")
    ap.add_argument("--script", nargs="+", required=True, help="phases seconds:v:w")
    ap.add_argument("--rate", type=float, default=20.0)
    ap.add_argument("--give-up", type=float, default=120.0, help="s to wait for --wait-for (a hang guard)")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    phases = [tuple(float(x) for x in p.split(":")) for p in a.script]

    T = rmw.STORE.types
    twist_t = "geometry_msgs/msg/Twist"
    session = rmw.session(a.connect)
    node = rmw.Node(session, a.domain, "teleop", "joystick")
    gid = rmw.gid(node.endpoint(1, "MP", "leader/cmd_vel", twist_t))
    pub = session.declare_publisher(rmw.key(a.domain, "leader/cmd_vel", twist_t))

    rmw.wait_for(session, a.domain, a.wait_for, a.wait_type, a.give_up, "joystick")
    print(f"joystick: /{a.wait_for} heard: playing {len(phases)} phase(s)", file=sys.stderr, flush=True)
    V3 = T["geometry_msgs/msg/Vector3"]
    sent, seq, tick = [], 1, time.monotonic()
    for seconds, v, w in phases:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            msg = T[twist_t](linear=V3(x=v, y=0.0, z=0.0), angular=V3(x=0.0, y=0.0, z=w))
            now = time.time_ns()
            pub.put(bytes(rmw.STORE.serialize_cdr(msg, twist_t)), attachment=rmw.attachment(seq, now, gid))
            sent.append([now, v, w])
            seq += 1
            tick += 1.0 / a.rate
            time.sleep(max(0.0, tick - time.monotonic()))
    node.close()
    session.close()
    with open(a.out, "w") as f:
        json.dump({"sent": sent}, f)
    print(f"joystick: {len(sent)} commands sent, then silent", file=sys.stderr)


if __name__ == "__main__":
    main()
