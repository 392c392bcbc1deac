#!/usr/bin/env python3
"""Reads the embeddings.npz of `dex2hoi evaluate --dump-embeddings` (the last replication's
clips) and prints how the generated objects turn against the ground truth's
(docs/results/shipped-model.md, "Objects that turn"):

- per task family and object slot, the median over clips of the largest turn from the clip's
  first frame and of the largest tilt of the object's up axis (+Y) from the vertical, for the
  ground truth and the generated clips;
- the median angle between the generated and the ground-truth rotation at a few frames, for
  the objects the ground truth leaves still (its position within 2 cm all clip) and for the
  ones it moves. The model generates a clip in windows (40 frames for the `demo` preset), so
  frame 40 is the first of the second window.

Needs numpy. usage: scripts/object-turns.py REPORT_DIR [REPORT_DIR ...]
"""
import sys

import numpy as np

STILL_METRES = 0.02
FRAMES = [0, 10, 20, 39, 40, 50, 59]


def angle(a, b):
    """Degrees of the rotation between the 3x3 matrices a and b (broadcast over leading axes)."""
    relative = np.einsum("...ij,...kj->...ik", a, b)
    cosine = (np.trace(relative, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))


def report(directory):
    z = np.load(directory + "/embeddings.npz")
    actions = np.array([str(a) or "(none)" for a in z["actions"]])
    generated = z["generated_object_rotations"]  # [N, T, 2, 3, 3]
    truth = z["ground_truth_object_rotations"]
    present = z["ground_truth_object_present"] > 0.5  # [N, 2]
    positions = z["ground_truth_object_positions"]  # [N, T, 2, 3]
    print(f"== {directory}")
    print("family         slot  turn from start (deg) truth / generated   tilt (deg) truth / generated")
    for family in sorted(set(actions)):
        for slot in range(2):
            clips = (actions == family) & present[:, slot]
            if not clips.any():
                continue

            def largest(rotations, what):
                r = rotations[clips, :, slot]
                if what == "turn":
                    return np.median(angle(r, r[:, :1]).max(axis=1))
                return np.median(np.degrees(np.arccos(np.clip(r[..., 1, 1], -1, 1))).max(axis=1))

            print(
                f"{family:14s} {slot:4d}  {largest(truth, 'turn'):9.1f} / {largest(generated, 'turn'):5.1f}"
                f"{largest(truth, 'tilt'):24.1f} / {largest(generated, 'tilt'):5.1f}"
            )
    error = angle(generated, truth).transpose(0, 2, 1)  # [N, 2, T]
    travel = np.linalg.norm(positions - positions[:, :1], axis=-1).max(axis=1)  # [N, 2]
    frames = [f for f in FRAMES if f < error.shape[2]]
    print("generated vs ground-truth rotation (deg, median) at frames", frames)
    for name, chosen in (
        ("objects the ground truth leaves still", present & (travel <= STILL_METRES)),
        ("objects the ground truth moves", present & (travel > STILL_METRES)),
    ):
        if not chosen.any():
            print(f"  {name}: none")
            continue
        values = np.median(error[chosen][:, frames], axis=0)
        print(f"  {name} ({chosen.sum()}):", " ".join(f"{v:5.1f}" for v in values))


if __name__ == "__main__":
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    for directory in sys.argv[1:]:
        report(directory)
