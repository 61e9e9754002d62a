"""Cross-check of a rosbag2 folder written by formation-ros2, read with
rosbags' rosbag2 Reader and with mcap-ros2-support (both independent).

Usage: check_bag.py DIR, where DIR/expected.json holds {"bag": path,
"topics": {name: {"type", "hash", "count", "reliability", "durability",
"depth"}}, "messages": [{"topic", "log_time", "expected"}]} (unique log
times). Checks:
- metadata.yaml: version 9, mcap, jazzy, the file list, counts, times,
  each topic's type, hash and QoS;
- rosbags' Reader: every connection's type, digest, count and QoS, and
  every message decoding (Jazzy store) to the expected fields, in order;
- mcap_ros2's read_ros2_messages: every message decoding with the schema
  text we wrote to the expected fields; schemas, channel metadata and the
  `rosbag2` metadata record.
Prints one line per failure and exits 1 if there is any.
"""

import json
import sys
from pathlib import Path

from mcap.reader import make_reader
from mcap_ros2.reader import read_ros2_messages
from rosbags.rosbag2 import Reader
from rosbags.rosbag2.metadata import parse_qos
from rosbags.typesys import Stores, get_typestore
from ruamel.yaml import YAML

from common import differences, plain


def check_metadata(bag, exp, msgs):
    failures = []
    info = YAML(typ="safe").load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    mcap_name = f"{bag.name}_0.mcap"
    times = [m["log_time"] for m in msgs]
    start, duration = (min(times), max(times) - min(times)) if times else (0, 0)
    want = {
        "version": 9, "storage_identifier": "mcap", "ros_distro": "jazzy",
        "relative_file_paths": [mcap_name], "message_count": len(msgs),
        "starting_time": {"nanoseconds_since_epoch": start}, "duration": {"nanoseconds": duration},
        "compression_format": "", "compression_mode": "",
    }
    for key, value in want.items():
        if info.get(key) != value:
            failures.append(f"metadata.yaml {key}: {info.get(key)!r}, want {value!r}")
    files = info.get("files", [])
    if len(files) != 1 or files[0].get("path") != mcap_name or files[0].get("message_count") != len(msgs):
        failures.append(f"metadata.yaml files: {files!r}")
    topics = {t["topic_metadata"]["name"]: t for t in info.get("topics_with_message_count", [])}
    if set(topics) != set(exp["topics"]):
        failures.append(f"metadata.yaml topics {sorted(topics)}, want {sorted(exp['topics'])}")
    for name, t in exp["topics"].items():
        got = topics.get(name)
        if not got:
            continue
        meta = got["topic_metadata"]
        if (meta["type"], meta["type_description_hash"], meta["serialization_format"], got["message_count"]) != (t["type"], t["hash"], "cdr", t["count"]):
            failures.append(f"metadata.yaml {name}: {got!r}")
        failures += check_qos(f"metadata.yaml {name}", parse_qos(meta["offered_qos_profiles"]), t)
    return failures


def check_qos(where, profiles, t):
    if len(profiles) != 1:
        return [f"{where}: {len(profiles)} QoS profiles"]
    q = profiles[0]
    got = (q.reliability.name.lower(), q.durability.name.lower(), q.history.name.lower(), q.depth)
    want = (t["reliability"], t["durability"], "keep_last", t["depth"])
    return [] if got == want else [f"{where}: QoS {got}, want {want}"]


def check_rosbags(bag, exp, msgs):
    failures = []
    jazzy = get_typestore(Stores.ROS2_JAZZY)
    with Reader(bag) as reader:
        for c in reader.connections:
            t = exp["topics"].get(c.topic)
            if t is None or (c.msgtype, c.digest, c.msgcount) != (t["type"], t["hash"], t["count"]):
                failures.append(f"rosbags connection {c.topic}: {c.msgtype} {c.digest} {c.msgcount}, want {t}")
            elif t:
                failures += check_qos(f"rosbags {c.topic}", c.ext.offered_qos_profiles, t)
        got = [(c.topic, ts, plain(jazzy.deserialize_cdr(raw, c.msgtype))) for c, ts, raw in reader.messages()]
    failures += compare_messages("rosbags", got, msgs)
    return failures


def check_mcap(bag, exp, msgs):
    failures = []
    path = bag / f"{bag.name}_0.mcap"
    got = [(m.channel.topic, m.log_time_ns, plain(m.ros_msg)) for m in read_ros2_messages(str(path))]
    failures += compare_messages("mcap_ros2", got, msgs)
    with open(path, "rb") as f:
        reader = make_reader(f)
        if reader.get_header().profile != "ros2":
            failures.append(f"mcap profile {reader.get_header().profile!r}")
        summary = reader.get_summary()
        for ch in summary.channels.values():
            t = exp["topics"].get(ch.topic, {})
            schema = summary.schemas[ch.schema_id]
            if (ch.message_encoding, schema.name, schema.encoding) != ("cdr", t.get("type"), "ros2msg"):
                failures.append(f"mcap {ch.topic}: {ch.message_encoding} {schema.name} {schema.encoding}")
            if ch.metadata.get("topic_type_hash") != t.get("hash"):
                failures.append(f"mcap {ch.topic}: topic_type_hash {ch.metadata.get('topic_type_hash')}")
            failures += check_qos(f"mcap {ch.topic}", parse_qos(ch.metadata.get("offered_qos_profiles", "")), t)
        records = [m for m in reader.iter_metadata() if m.name == "rosbag2"]
        yaml = YAML(typ="safe")
        file_info = yaml.load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
        if len(records) != 1 or yaml.load(records[0].metadata.get("serialized_metadata", "")) != file_info:
            failures.append("mcap: the rosbag2 metadata record is not metadata.yaml's body")
    return failures


def compare_messages(who, got, msgs):
    want = sorted(((m["topic"], m["log_time"], m["expected"]) for m in msgs), key=lambda m: m[1])
    if len(got) != len(want):
        return [f"{who}: {len(got)} messages, want {len(want)}"]
    failures = []
    for (gt, gts, gv), (wt, wts, wv) in zip(got, want):
        if (gt, gts) != (wt, wts):
            failures.append(f"{who}: message ({gt}, {gts}), want ({wt}, {wts})")
        failures += [f"{who} {wt} @{wts} {d}" for d in differences(gv, wv)]
    return failures


def main():
    exp = json.loads((Path(sys.argv[1]) / "expected.json").read_text())
    bag, msgs = Path(exp["bag"]), exp["messages"]
    failures = []
    for check in (check_metadata, check_rosbags, check_mcap):
        try:
            failures += check(bag, exp, msgs)
        except Exception as e:  # a reader's exception is a failure to report
            failures.append(f"{check.__name__}: {type(e).__name__}: {e}")
    for f in failures:
        print(f)
    print(f"check_bag: {len(msgs)} messages on {len(exp['topics'])} topics, {len(failures)} failures")
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    main()
