"""Cross-check of formation-ros2's CDR payloads, hashes and definitions
against rosbags (an independent implementation).

Usage: check_cdr.py DIR, where DIR/manifest.json lists samples
{"file", "type", "hash", "definition", "expected"} written by the Rust test.
For each sample:
- rosbags' Jazzy typestore decodes the payload to the expected fields,
  and re-encodes it to the very same bytes;
- rosbags' hash_rihs01 of the type equals our HASH;
- our DEFINITION parses (get_types_from_msg) to the Jazzy store's types,
  and a store holding only those types hashes to our HASH.
Prints one line per failure and exits 1 if there is any.
"""

import json
import sys
from pathlib import Path

from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from common import differences, plain


def check(sample, data, jazzy):
    name = sample["type"]
    failures = []
    decoded = jazzy.deserialize_cdr(data, name)
    failures += [f"{name} fields {d}" for d in differences(plain(decoded), sample["expected"])]
    again = bytes(jazzy.serialize_cdr(decoded, name))
    if again != data:
        failures.append(f"{name}: rosbags re-encodes {len(again)} bytes {again.hex()}, ours are {len(data)} bytes {data.hex()}")
    if (h := jazzy.hash_rihs01(name)) != sample["hash"]:
        failures.append(f"{name}: rosbags' Jazzy hash {h}, ours {sample['hash']}")
    parsed = get_types_from_msg(sample["definition"], name)
    for t, fields in parsed.items():
        if t not in jazzy.fielddefs or tuple(fields) != tuple(jazzy.fielddefs[t]):
            failures.append(f"{name}: our definition of {t} parses to {fields}, Jazzy has {jazzy.fielddefs.get(t)}")
    own = get_typestore(Stores.EMPTY)
    own.register(parsed)
    if (h := own.hash_rihs01(name)) != sample["hash"]:
        failures.append(f"{name}: our definition hashes to {h} in rosbags, HASH is {sample['hash']}")
    return failures


def main():
    root = Path(sys.argv[1])
    samples = json.loads((root / "manifest.json").read_text())
    jazzy = get_typestore(Stores.ROS2_JAZZY)
    failures = []
    for sample in samples:
        try:
            failures += check(sample, (root / sample["file"]).read_bytes(), jazzy)
        except Exception as e:  # a decoder's exception is a failure to report
            failures.append(f"{sample['type']} ({sample['file']}): {type(e).__name__}: {e}")
    for f in failures:
        print(f)
    print(f"check_cdr: {len(samples)} payloads, {len(failures)} failures")
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    main()
