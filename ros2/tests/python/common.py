"""Helpers shared by the cross-checks: decoded messages as plain values."""

import dataclasses


def plain(value):
    """A decoded message (rosbags dataclass or mcap_ros2 slots object) as
    dicts, lists and scalars; numpy arrays become lists of floats."""
    if dataclasses.is_dataclass(value):
        names = [f.name for f in dataclasses.fields(value)]
    elif hasattr(value, "__slots__") and not isinstance(value, (str, bytes)):
        names = list(value.__slots__)
    else:
        names = None
    if names is not None:  # a message: its fields, not rosbags' __msgtype__
        return {k: plain(getattr(value, k)) for k in names if not k.startswith("__")}
    if hasattr(value, "tolist"):  # numpy arrays and scalars
        return plain(value.tolist())
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    return value


def differences(got, want, where=""):
    """Every path at which `got` differs from `want`, with both values."""
    if isinstance(want, dict) and isinstance(got, dict):
        out = []
        for key in sorted(set(want) | set(got)):
            if key not in got or key not in want:
                out.append(f"{where}.{key}: present in only one of got/want")
            else:
                out += differences(got[key], want[key], f"{where}.{key}")
        return out
    if isinstance(want, list) and isinstance(got, list):
        if len(got) != len(want):
            return [f"{where}: {len(got)} elements, want {len(want)}"]
        return [d for i, (g, w) in enumerate(zip(got, want)) for d in differences(g, w, f"{where}[{i}]")]
    return [] if got == want else [f"{where}: got {got!r}, want {want!r}"]
