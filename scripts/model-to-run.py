#!/usr/bin/env python3
"""Turns a packed model (`dex2hoi model pack`, such as the shipped
crates/dex2hoi-cli/model/dex2hoi-demo.safetensors) into a run directory that
`dex2hoi train --resume` continues: a fine-tuning start for the training studies of
docs/results/ when the model's own run directory is gone.

A packed model keeps the EMA weights only, so the checkpoint written here has those as both
the trained parameters and their EMA, zero AdamW moments, step 0 and no optimiser updates:
AdamW starts afresh (its warm-up included) from the model's weights, with the model's stored
training configuration, normalisation statistics, dataset manifest and vocabulary. Train it on
data with the model's vocabulary (`train --resume` checks) and, for the statistics to mean the
same, the dataset it was trained on. A setting can be changed for the continuation as with any
run copy (scripts/retarget-checkpoint.py, or scripts/gpu-train.sh's GPU_TRAIN_RESUME).

usage: scripts/model-to-run.py MODEL.safetensors RUN_DIR
"""
import json
import os
import struct
import sys

if len(sys.argv) != 3:
    sys.exit(__doc__)
model, run = sys.argv[1:3]
try:
    with open(model, 'rb') as f:
        n = struct.unpack('<Q', f.read(8))[0]
        header = json.loads(f.read(n))
        data = f.read()
    metadata = header.pop('__metadata__')
    if metadata.get('dex2hoi.model_format') != 'dex2hoi-model-1':
        raise ValueError(f"model format {metadata.get('dex2hoi.model_format')!r}, expected 'dex2hoi-model-1'")
    train_config = metadata['dex2hoi.train_config']
    manifest = metadata['dex2hoi.manifest']
    stats = metadata['dex2hoi.stats']
except (OSError, ValueError, KeyError, struct.error) as e:
    sys.exit(f'{model}: expected a packed dex2hoi model (safetensors with dex2hoi.model_format): {e}')

tensors = {}
chunks = []
offset = 0


def add(name, dtype, shape, payload):
    global offset
    tensors[name] = {'dtype': dtype, 'shape': shape, 'data_offsets': [offset, offset + len(payload)]}
    chunks.append(payload)
    offset += len(payload)


for name, entry in sorted(header.items()):
    if not name.startswith('ema.'):
        sys.exit(f'{model}: tensor {name!r}, expected EMA weights only (ema.*)')
    if entry['dtype'] != 'F32':
        sys.exit(f'{model}: tensor {name!r} is {entry["dtype"]}, expected F32 (pack without --f16)')
    start, end = entry['data_offsets']
    payload = data[start:end]
    parameter = name[len('ema.'):]
    add(parameter, 'F32', entry['shape'], payload)
    add(name, 'F32', entry['shape'], payload)
    add('optimizer.first.' + parameter, 'F32', entry['shape'], bytes(len(payload)))
    add('optimizer.second.' + parameter, 'F32', entry['shape'], bytes(len(payload)))

checkpoint_metadata = {
    k: v for k, v in metadata.items()
    if k not in ('dex2hoi.model_format', 'dex2hoi.manifest', 'dex2hoi.stats')
}
checkpoint_metadata['dex2hoi.step'] = '0'
checkpoint_metadata['dex2hoi.optimizer_updates'] = '0'
tensors['__metadata__'] = checkpoint_metadata
raw = json.dumps(tensors, separators=(',', ':')).encode()
raw += b' ' * ((8 - len(raw) % 8) % 8)

os.makedirs(run, exist_ok=True)
if os.path.exists(os.path.join(run, 'checkpoint.safetensors')):
    sys.exit(f'{run}: already holds a checkpoint; expected a new run directory')


def write(name, payload):
    path = os.path.join(run, name)
    with open(path + '.tmp', 'wb') as f:
        f.write(payload)
    os.replace(path + '.tmp', path)


write('config.toml', train_config.encode())
write('dataset.json', manifest.encode())
write('stats.json', stats.encode())
write('metrics.jsonl', b'')
write('checkpoint.safetensors', struct.pack('<Q', len(raw)) + raw + b''.join(chunks))
print(f'{run}: a run at step 0 initialised from {model} (step {metadata.get("dex2hoi.step")})')
