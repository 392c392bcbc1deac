#!/usr/bin/env python3
"""Reads the samples of scripts/long-samples.sh and prints, per folder, what happens to the
objects over 160 frames (docs/results/shipped-model.md, "Long generations"): for each object
track, its deepest point below where it stood (cm), the share of frames it is more than 1 cm
below that, and the speed of objects no hand is near (both wrists more than 25 cm from the
object's centre), with the mean deepest sink per task family. Needs numpy.

usage: scripts/long-samples.py OUT_DIR [OUT_DIR ...]
"""
import collections
import glob
import os
import sys

import numpy as np

UNTOUCHED_METRES = 0.25
LOW_METRES = 0.01


def tracks(folder):
    found = []
    for path in sorted(glob.glob(os.path.join(folder, '*', 'motion.npz'))):
        motion = np.load(path)
        names = [str(n) for n in motion['joint_names']]
        wrists = motion['joints'][:, [names.index('left_wrist'), names.index('right_wrist')]]
        fps = float(motion['fps'])
        family = os.path.basename(os.path.dirname(path)).rsplit('-', 1)[0]
        for positions in motion['object_translations']:
            below = positions[0, 1] - positions[:, 1]  # +Y is up
            nearest = np.linalg.norm(wrists - positions[:, None, :], axis=2).min(axis=1)
            speed = np.linalg.norm(np.diff(positions, axis=0), axis=1) * fps
            untouched = (nearest[1:] > UNTOUCHED_METRES) & (nearest[:-1] > UNTOUCHED_METRES)
            found.append({'family': family, 'sink_cm': max(0.0, below.max()) * 100,
                          'low_percent': (below > LOW_METRES).mean() * 100,
                          'untouched_cm_s': speed[untouched] * 100})
    return found


def main(folders):
    if not folders:
        sys.exit(__doc__)
    for folder in folders:
        found = tracks(folder)
        if not found:
            sys.exit(f'{folder}: expected sample folders with motion.npz (scripts/long-samples.sh)')
        sinks = np.array([t['sink_cm'] for t in found])
        untouched = np.concatenate([t['untouched_cm_s'] for t in found])
        families = collections.defaultdict(list)
        for t in found:
            families[t['family']].append(t['sink_cm'])
        speed = f'{np.median(untouched):.1f} cm/s' if len(untouched) else '-'
        print(f'{folder}: {len(found)} object tracks; deepest sink mean {sinks.mean():.2f}, '
              f'median {np.median(sinks):.2f}, 90th percentile {np.percentile(sinks, 90):.2f} cm; '
              f'frames more than 1 cm low {np.mean([t["low_percent"] for t in found]):.1f}%; '
              f'untouched speed median {speed}')
        print('  mean deepest sink per family (cm): ' +
              ', '.join(f'{k} {np.mean(v):.1f}' for k, v in sorted(families.items())))


if __name__ == '__main__':
    main(sys.argv[1:])
