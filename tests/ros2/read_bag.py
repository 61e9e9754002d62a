"""Reads a run folder's rosbag2/ with two readers that are not the
formation's code — rosbags' rosbag2 Reader (metadata.yaml, the MCAP file,
CDR by its own type store) and mcap-ros2-support (decoding by the bag's own
ros2msg schemas) — and writes per topic: its type, how many messages each
reader decoded, and the first and last odometry poses.

    python read_bag.py RUN_DIR/rosbag2 --out bag.json
"""
import argparse
import json
import math
import sys

from mcap_ros2.reader import read_ros2_messages
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("bag")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    store = get_typestore(Stores.ROS2_JAZZY)
    topics = {}
    with Reader(a.bag) as reader:
        for c in reader.connections:
            topics[c.topic] = {"type": c.msgtype, "hash": c.digest, "counted": c.msgcount,
                               "rosbags": 0, "mcap_ros2": 0, "poses": []}
        for c, t, raw in reader.messages():
            m = store.deserialize_cdr(raw, c.msgtype)
            entry = topics[c.topic]
            entry["rosbags"] += 1
            if c.msgtype == "nav_msgs/msg/Odometry":
                p, q = m.pose.pose.position, m.pose.pose.orientation
                entry["poses"].append([t, p.x, p.y, 2 * math.atan2(q.z, q.w)])
    mcap_file = [p for p in __import__("pathlib").Path(a.bag).glob("*.mcap")]
    if len(mcap_file) != 1:
        sys.exit(f"expected one .mcap file in {a.bag}, found {len(mcap_file)}")
    for m in read_ros2_messages(str(mcap_file[0])):
        topics[m.channel.topic]["mcap_ros2"] += 1
    for e in topics.values():
        if e["poses"]:
            e["first_pose"], e["last_pose"] = e["poses"][0], e["poses"][-1]
        e["poses_count"] = len(e["poses"])
        del e["poses"]
    with open(a.out, "w") as f:
        json.dump(topics, f, indent=1)


if __name__ == "__main__":
    main()
