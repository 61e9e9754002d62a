"""rmw_zenoh's wire for the test scripts, written from its source, not from
the formation's code: a client session without multicast, the data key of
a topic, a node's and an endpoint's liveliness tokens, and the 33-byte
attachment (sequence number, source time, publisher GID) without which
rmw_zenoh drops a sample."""
import hashlib
import json
import struct
import sys
import threading

import zenoh
from rosbags.typesys import Stores, get_typestore

STORE = get_typestore(Stores.ROS2_JAZZY)


def session(connect):
    """A client session to `connect`, multicast scouting off."""
    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([connect]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def dds(typename):
    """`nav_msgs/msg/Odometry` as rmw_zenoh names it, with its RIHS01 hash."""
    pkg, kind, name = typename.split("/")
    return f"{pkg}::{kind}::dds_::{name}_/{STORE.hash_rihs01(typename)}"


def key(domain, topic, typename):
    """The data key of `topic` (absolute, without the leading /)."""
    return f"{domain}/{topic.strip('/')}/{dds(typename)}"


class Node:
    """A ROS 2 node's liveliness tokens on `s`: the node's, then one per
    endpoint (kind MP: publisher, MS: subscription)."""

    def __init__(self, s, domain, namespace, name):
        self.s, self.domain, self.ns, self.name = s, domain, namespace.strip("/"), name
        self.zid = str(s.info.zid())
        self.tokens = [s.liveliness().declare_token(f"@ros2_lv/{domain}/{self.zid}/0/0/NN/%/%{self.ns}/{name}")]

    def endpoint(self, eid, kind, topic, typename):
        """Declares an endpoint's token; its key (a publisher's GID is made from it)."""
        mangled = "%" + topic.strip("/").replace("/", "%")
        token = (f"@ros2_lv/{self.domain}/{self.zid}/0/{eid}/{kind}/%/%{self.ns}/{self.name}/{mangled}/"
                 f"{dds(typename)}/::,10:,:,:,,")
        self.tokens.append(self.s.liveliness().declare_token(token))
        return token

    def close(self):
        for t in self.tokens:
            t.undeclare()


def gid(token):
    """A publisher's GID: the first 16 bytes of its token's SHA-256."""
    return hashlib.sha256(token.encode()).digest()[:16]


def attachment(seq, source_ns, publisher_gid):
    """rmw_zenoh's attachment: i64 sequence, i64 source time, GID length, GID."""
    return struct.pack("<qq", seq, source_ns) + bytes([16]) + publisher_gid


def wait_for(s, domain, topic, typename, give_up, who):
    """Until `topic` carries a message (the run it serves has started); exits
    naming it after `give_up` seconds (a hang guard)."""
    heard = threading.Event()
    sub = s.declare_subscriber(key(domain, topic, typename), lambda _s: heard.set())
    ok = heard.wait(give_up)
    sub.undeclare()
    if not ok:
        print(f"{who}: nothing on /{topic} within {give_up} s", file=sys.stderr)
        sys.exit(1)
