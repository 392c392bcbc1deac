#!/usr/bin/env python3
"""Rewrites one line of the training configuration stored in a checkpoint, so that
`dex2hoi train --resume` continues a copy of a run under a changed setting, such as a loss
weight: a continuation with another objective, no longer a bit-exact resume (which is why
`train --resume` refuses a changed configuration). Used for the annealed continuations of
docs/results/steps.md ("Continuations of the world run under other settings"). Work on a
copy of the run directory, and pass the same change in the `--config` file given to
`train --resume`.

usage: scripts/retarget-checkpoint.py CHECKPOINT 'OLD LINE' 'NEW LINE'
   e.g. scripts/retarget-checkpoint.py runs/copy/checkpoint.safetensors 'distance = 1.0' 'distance = 3.0'
"""
import json
import os
import struct
import sys

if len(sys.argv) != 4:
    sys.exit(__doc__)
path, old, new = sys.argv[1:4]
try:
    with open(path, 'rb') as f:
        n = struct.unpack('<Q', f.read(8))[0]
        header = json.loads(f.read(n))
        data = f.read()
    config = header['__metadata__']['dex2hoi.train_config']
except (OSError, ValueError, KeyError, struct.error) as e:
    sys.exit(f'{path}: expected a dex2hoi checkpoint (safetensors with a training configuration): {e}')
if config.count(old + '\n') != 1:
    sys.exit(f'{path}: the stored configuration has the line {old!r} {config.count(old + chr(10))} times, expected once')
header['__metadata__']['dex2hoi.train_config'] = config.replace(old + '\n', new + '\n')
raw = json.dumps(header, separators=(',', ':')).encode()
raw += b' ' * ((8 - len(raw) % 8) % 8)
temporary = path + '.tmp'
with open(temporary, 'wb') as f:
    f.write(struct.pack('<Q', len(raw)))
    f.write(raw)
    f.write(data)
os.replace(temporary, path)
print(f'{path}: {old!r} -> {new!r}')
