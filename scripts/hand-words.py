#!/usr/bin/env python3
"""Reads the samples of scripts/hand-words.sh: per sample, the hand asked for and the hand that
held the mug (the wrist within 20 cm of the mug's centre, median over the frames it is lifted
more than 3 cm), the side asked for and the side it ended on (more than 3 cm from where it
stood; "back" asks for its own place), and the lifts; then how many samples got the hand and
the side right; last, for each hand and seed, how far apart "to the left" and "to the right" put
the mug down (same noise, only the side word differs: near 0 when the words go unread).

    scripts/hand-words.py OUT_DIR
"""
import os
import sys

import numpy as np

LIFTED = 0.03  # metres above where it stood
NEAR = 0.20  # metres from the wrist to the mug's centre
MOVED = 0.03  # metres sideways: less is "back"


def read(path):
    data = np.load(path)
    names = [str(n) for n in data["joint_names"]]
    mug = data["object_translations"][0]  # [frames, 3]; +X is the person's left
    joints = data["joints"]
    wrists = {side: joints[:, names.index(f"{name}_wrist")] for side, name in (("L", "left"), ("R", "right"))}
    up = mug[:, 1] - mug[0, 1] > LIFTED
    lifts = int(np.sum(up[1:] & ~up[:-1]) + up[0])
    held = ""
    if up.any():
        for side, wrist in wrists.items():
            if np.median(np.linalg.norm(wrist[up] - mug[up], axis=1)) < NEAR:
                held += side
    moved = mug[-1, 0] - mug[0, 0]
    ended = "left" if moved > MOVED else "right" if moved < -MOVED else "back"
    return held or "-", ended, lifts, moved


def main():
    if len(sys.argv) != 2:
        sys.exit(__doc__)
    root = sys.argv[1]
    right_hand = right_side = total = 0
    travels = {}
    for name in sorted(os.listdir(root)):
        path = os.path.join(root, name, "motion.npz")
        if not os.path.isfile(path):
            continue
        parts = name.split("-")
        if len(parts) != 4:
            continue
        task, hand, side, seed = parts
        held, ended, lifts, moved = read(path)
        travels[(task, hand, side, seed)] = moved
        total += 1
        right_hand += held == hand
        right_side += ended == side
        print(f"{name:18s} hand asked {hand}, held {held:2s}  side asked {side:5s}, ended {ended:5s}  lifts {lifts}")
    if total:
        print(f"the hand asked for: {right_hand} of {total}; the side asked for: {right_side} of {total}")
    apart = []
    for (task, hand, side, seed), left in sorted(travels.items()):
        right = travels.get((task, hand, "right", seed))
        if side != "left" or right is None:
            continue
        apart.append(left - right)
        print(f"{task}-{hand} seed {seed}: to the left ends {left * 100:+.1f} cm, to the right {right * 100:+.1f} cm")
    if apart:
        print(f"the side words move where the mug ends by a median {np.median(apart) * 100:+.1f} cm (left minus right)")


if __name__ == "__main__":
    main()
