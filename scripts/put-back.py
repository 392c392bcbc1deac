#!/usr/bin/env python3
"""Where generated objects end against where the ground truth puts them: for every sample in
GEN_DIR with a ground truth of the same name in GT_DIR (each NAME/motion.npz, from
`dex2hoi sample --data D --sequence S` and `dex2hoi data show D --sequence S`), each object the
ground truth moves (the long protocol's rule: travel beyond 10 cm or a rise beyond 5 cm), how
far the generated one ends from where the ground truth's ends: along the body's left axis at the
first frame (positive: to the person's left) and in the plane of the table, cm, and how long
each holds it up (from the first to the last frame more than 3 cm above where it stood, s);
then the median misses, the share within the 5 cm of the long protocol's centre band and the
median times held up.

    scripts/put-back.py GEN_DIR GT_DIR
"""
import glob
import os
import sys

import numpy as np

MOVED_TRAVEL = 0.10  # metres in the plane of the table
MOVED_RISE = 0.05  # metres up
CENTRE_BAND = 0.05  # metres along the left axis
LIFTED = 0.03  # metres above where it stood
FPS = 20.0


def load(path):
    """Object positions [objects, frames, 3], the body's left axis at the first frame, text."""
    motion = np.load(path)
    names = list(motion["joint_names"])
    joints = motion["joints"][0]
    left = joints[names.index("left_hip")] - joints[names.index("right_hip")]
    left[1] = 0.0
    return motion["object_translations"], left / np.linalg.norm(left), str(motion["text"])


def held_up(track):
    """Seconds from the first to the last frame the object is more than LIFTED above its start."""
    up = (track[:, 1] - track[0, 1] > LIFTED).nonzero()[0]
    return (up[-1] - up[0] + 1) / FPS if len(up) else 0.0


def main():
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    generated, truth = sys.argv[1], sys.argv[2]
    lateral, planar, held = [], [], []
    for path in sorted(glob.glob(os.path.join(generated, "*", "motion.npz"))):
        name = os.path.basename(os.path.dirname(path))
        reference = os.path.join(truth, name, "motion.npz")
        if not os.path.exists(reference):
            continue
        ours, left, text = load(path)
        theirs, _, _ = load(reference)
        for k, (p, q) in enumerate(zip(ours, theirs)):
            travel = np.linalg.norm((q - q[0])[:, [0, 2]], axis=1).max()
            if travel <= MOVED_TRAVEL and (q[:, 1] - q[0, 1]).max() <= MOVED_RISE:
                continue
            miss = p[-1] - q[-1]
            lateral.append(miss @ left)
            planar.append(np.linalg.norm(miss[[0, 2]]))
            held.append((held_up(p), held_up(q)))
            print(f"{name:14s} object {k}: lateral miss {100 * lateral[-1]:6.1f} cm, "
                  f"planar {100 * planar[-1]:5.1f} cm, held up {held[-1][0]:4.1f} s "
                  f"(ground truth {held[-1][1]:4.1f} s)   {text[:50]}")
    if not lateral:
        sys.exit(f"no sample in {generated} has a ground truth that moves an object in {truth}")
    lateral = np.abs(np.array(lateral))
    print(f"{len(lateral)} moved objects: median lateral miss {100 * np.median(lateral):.1f} cm "
          f"({100 * np.mean(lateral <= CENTRE_BAND):.0f}% within {100 * CENTRE_BAND:.0f} cm), "
          f"median planar miss {100 * np.median(planar):.1f} cm; held up a median "
          f"{np.median([h for h, _ in held]):.1f} s (ground truth {np.median([h for _, h in held]):.1f} s)")


if __name__ == "__main__":
    main()
