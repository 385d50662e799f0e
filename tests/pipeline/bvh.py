"""A strict reader of BVH files for the tests of the rig's export (structure checked as it reads)."""

from __future__ import annotations

import numpy as np


def parse_bvh(text):
    """Joints (name, parent, offset, channels) and motion rows of a BVH file; strict about structure."""
    tok = text.split()
    i = 0
    assert tok[i] == "HIERARCHY"
    i += 1
    joints, stack, pending = [], [], None
    while tok[i] != "MOTION":
        t = tok[i]
        if t in ("ROOT", "JOINT"):
            parents = [x for x in stack if x is not None]
            joints.append({"name": tok[i + 1], "parent": parents[-1] if parents else None})
            pending = len(joints) - 1
            i += 2
        elif t == "End":
            assert tok[i + 1] == "Site"
            pending = None
            i += 2
        elif t == "{":
            stack.append(pending)
            i += 1
        elif t == "}":
            stack.pop()
            i += 1
        elif t == "OFFSET":
            if stack[-1] is not None:
                joints[stack[-1]]["offset"] = [float(x) for x in tok[i + 1 : i + 4]]
            i += 4
        elif t == "CHANNELS":
            n = int(tok[i + 1])
            joints[stack[-1]]["channels"] = tok[i + 2 : i + 2 + n]
            i += 2 + n
        else:
            raise AssertionError(f"unexpected BVH token {t!r}")
    assert not stack
    assert tok[i + 1] == "Frames:"
    frames = int(tok[i + 2])
    assert tok[i + 3 : i + 5] == ["Frame", "Time:"]
    n_ch = sum(len(j["channels"]) for j in joints)
    rows = np.asarray(tok[i + 6 :], dtype=float).reshape(frames, n_ch)
    return joints, rows
