#!/usr/bin/env python3
"""Whether a model lifts the vessel a pour only steadies: samples the first N pours of a
dataset's test split (200 frames from the sequence's first frame, seed 0, `sample`'s defaults)
and counts, per generation, the objects lifted (above 3 cm over where they stood for at least
0.25 s, lifts less than 0.5 s apart merged, as the long protocol counts them). In the data a
pour lifts one object once, the one poured from: a generation that lifts both has lifted the
vessel poured into, and an object lifted twice was lifted again unasked.

    scripts/pour-check.py MODEL DATA OUT_DIR [N]   # MODEL: a packed model file or a run

DEX2HOI (default target/release/dex2hoi) is the binary. Samples already in OUT_DIR are kept.
"""
import json
import os
import subprocess
import sys

import numpy as np

FPS = 20
LIFTED = 0.03  # metres above where it stood
MIN_LIFT_S = 0.25
MERGE_S = 0.5


def lifts(heights):
    """The lifts of one object's height course (metres above its start), as frame ranges."""
    runs, start = [], None
    for frame, up in enumerate(list(heights > LIFTED) + [False]):
        if up and start is None:
            start = frame
        if not up and start is not None:
            runs.append([start, frame])
            start = None
    merged = []
    for a, b in runs:
        if merged and a - merged[-1][1] < MERGE_S * FPS:
            merged[-1][1] = b
        else:
            merged.append([a, b])
    return [r for r in merged if r[1] - r[0] >= MIN_LIFT_S * FPS]


def main():
    if len(sys.argv) not in (4, 5):
        sys.exit(__doc__)
    model, data, out = sys.argv[1:4]
    count = int(sys.argv[4]) if len(sys.argv) == 5 else 25
    binary = os.environ.get("DEX2HOI", "target/release/dex2hoi")
    with open(os.path.join(data, "test.json")) as f:
        pours = [s for s in json.load(f) if s["action"] == "pour"][:count]
    if not pours:
        sys.exit(f"{data}/test.json has no pour sequences")
    both = twice = 0
    for sequence in pours:
        name = sequence["source_id"]
        sample = os.path.join(out, name)
        if not os.path.exists(os.path.join(sample, "motion.npz")):
            subprocess.run(
                [binary, "sample", "--run", model, "--data", data, "--sequence", name,
                 "--frames", "200", "--seed", "0", "--out", sample],
                check=True, capture_output=True)
        objects = np.load(os.path.join(sample, "motion.npz"))["object_translations"]
        counts = [len(lifts(o[:, 1] - o[0, 1])) for o in objects]
        both += sum(1 for c in counts if c > 0) > 1
        twice += sum(1 for c in counts if c > 1)
        print(f"{name}  lifts per object {counts}  {sequence['texts'][0]}")
    print(f"{len(pours)} pours: both objects lifted in {both}, objects lifted more than once: "
          f"{twice}")


if __name__ == "__main__":
    main()
