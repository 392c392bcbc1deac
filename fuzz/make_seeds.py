"""Writes the seed corpora of the fuzz targets into fuzz/corpus/<target>/ (committed; rerun to
regenerate). Small valid files of every kind each reader accepts, so that the fuzzer starts
from the formats' structure. Needs numpy. The `regression-*` files beside them are inputs the
fuzzers once crashed on (kept as seeds: `cargo xtask fuzz check`, part of CI, replays them)."""
import io
import json
import os
import pickle
import struct
import sys
import zipfile

import numpy as np

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'corpus')


def put(target, name, data):
    folder = os.path.join(ROOT, target)
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, name), 'wb') as fh:
        fh.write(data)


def npy_bytes(array, allow_pickle=False):
    buffer = io.BytesIO()
    np.save(buffer, array, allow_pickle=allow_pickle)
    return buffer.getvalue()


def npz_bytes(compressed, **arrays):
    buffer = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buffer, **arrays)
    return buffer.getvalue()


def pickles():
    value = {'armature': [{'mixamorig:Hips': [1.0, 0, 0, 0, 0.0, 0.01, -0.02]}],
             'objects': {'mug': [[1.0, 0, 0, 0, 0.1, 0.2, 0.3]]},
             'object_models': {'mug': {'mesh': (np.zeros((3, 3), np.float32),
                                                np.array([[0, 1, 2]], np.int64))}},
             'text': 'pick up the mug', 'n': 3, 'flag': True, 'none': None, 't': (1, 2.5)}
    for protocol in (2, 3, 4, 5):
        put('pickle', f'dict_protocol{protocol}.pkl', pickle.dumps(value, protocol=protocol))
    put('pickle', 'array_f8.pkl', pickle.dumps(np.arange(6.0).reshape(2, 3), protocol=2))
    put('pickle', 'array_fortran_i2.pkl',
        pickle.dumps(np.asfortranarray(np.arange(6, dtype='>i2').reshape(2, 3)), protocol=4))


def npys():
    put('npy', 'f4.npy', b'\x00' + npy_bytes(np.arange(12, dtype=np.float32).reshape(3, 4)))
    put('npy', 'u1_fortran.npy', b'\x00' + npy_bytes(np.asfortranarray(np.eye(3, dtype=np.uint8))))
    put('npy', 'unicode.npy', b'\x00' + npy_bytes(np.array(['left', 'right'])))
    put('npy', 'object_dict.npy', b'\x00' + npy_bytes(
        np.array({'transl': np.zeros((2, 3), np.float32)}, dtype=object), allow_pickle=True))
    put('npy', 'stored.npz', b'\x01' + npz_bytes(False, a=np.arange(4.0), b=np.array(3)))
    put('npy', 'deflated.npz', b'\x01' + npz_bytes(True, betas=np.zeros(10, np.float32),
                                                   transl=np.ones((2, 3), np.float32)))


def meshes():
    obj = b'# a square\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1 4//1\n'
    put('mesh', 'square.obj', b'\x00' + obj)
    header = ('ply\nformat {}\ncomment made by make_seeds.py\nelement vertex 3\nproperty float x\n'
              'property float y\nproperty float z\nelement face 1\n'
              'property list uchar int vertex_indices\nend_header\n')
    put('mesh', 'ascii.ply', b'\x01' + header.format('ascii 1.0').encode()
        + b'0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n')
    body = struct.pack('<9f', 0, 0, 0, 1, 0, 0, 0, 1, 0) + struct.pack('<B3i', 3, 0, 1, 2)
    put('mesh', 'binary_le.ply', b'\x01' + header.format('binary_little_endian 1.0').encode() + body)


def glb():
    """A skinned two-joint scene with a triangle, its animation (LINEAR translation, STEP
    rotation) and an animated, unskinned object node."""
    blobs = []
    views = []
    accessors = []

    def add(array, kind, component=5126, count=None):
        data = np.ascontiguousarray(array).tobytes()
        offset = sum(len(b) for b in blobs)
        blobs.append(data + b'\x00' * (-len(data) % 4))
        views.append({'buffer': 0, 'byteOffset': offset, 'byteLength': len(data)})
        accessor = {'bufferView': len(views) - 1, 'componentType': component,
                    'count': count if count is not None else len(array), 'type': kind}
        if kind == 'VEC3' and component == 5126:
            accessor['min'] = np.min(array, axis=0).tolist()
            accessor['max'] = np.max(array, axis=0).tolist()
        accessors.append(accessor)
        return len(accessors) - 1

    positions = add(np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]], np.float32), 'VEC3')
    indices = add(np.array([0, 1, 2], np.uint16), 'SCALAR', 5123)
    joints = add(np.zeros((3, 4), np.uint16), 'VEC4', 5123)
    weights = add(np.tile(np.array([1, 0, 0, 0], np.float32), (3, 1)), 'VEC4')
    inverse_bind = add(np.stack([np.eye(4, dtype=np.float32).T.reshape(16),
                                 np.array(np.linalg.inv(np.array([[1, 0, 0, 0], [0, 1, 0, 0.5],
                                                                  [0, 0, 1, 0], [0, 0, 0, 1]],
                                                                 np.float32)).T.reshape(16),
                                          np.float32)]), 'MAT4')
    times = add(np.array([0.0, 1 / 30, 2 / 30], np.float32), 'SCALAR')
    accessors[times]['min'] = [0.0]
    accessors[times]['max'] = [2 / 30]
    moves = add(np.array([[0, 0.9, 0], [0, 0.91, 0.01], [0, 0.92, 0.02]], np.float32), 'VEC3')
    turns = add(np.array([[0, 0, 0, 1], [0, 0.0998, 0, 0.995], [0, 0.1987, 0, 0.98]], np.float32),
                'VEC4')
    document = {
        'asset': {'version': '2.0', 'generator': 'dex2hoi fuzz/make_seeds.py'},
        'scene': 0,
        'scenes': [{'nodes': [0, 3]}],
        'nodes': [
            {'name': 'Armature', 'children': [1, 4], 'scale': [0.01, 0.01, 0.01]},
            {'name': 'mixamorig:Hips', 'children': [2], 'translation': [0, 88.0, 0]},
            {'name': 'mixamorig:Spine', 'translation': [0, 6.5, -0.9]},
            {'name': 'cup', 'mesh': 0, 'translation': [0.3, 0.8, 0.2]},
            {'name': 'body', 'mesh': 0, 'skin': 0},
        ],
        'meshes': [{'name': 'triangle', 'primitives': [{'attributes': {
            'POSITION': positions, 'JOINTS_0': joints, 'WEIGHTS_0': weights}, 'indices': indices}]}],
        'skins': [{'joints': [1, 2], 'inverseBindMatrices': inverse_bind}],
        'animations': [{'name': 'motion', 'channels': [
            {'sampler': 0, 'target': {'node': 1, 'path': 'translation'}},
            {'sampler': 1, 'target': {'node': 2, 'path': 'rotation'}},
            {'sampler': 0, 'target': {'node': 3, 'path': 'translation'}},
        ], 'samplers': [
            {'input': times, 'output': moves, 'interpolation': 'LINEAR'},
            {'input': times, 'output': turns, 'interpolation': 'STEP'},
        ]}],
        'accessors': accessors,
        'bufferViews': views,
        'buffers': [{'byteLength': sum(len(b) for b in blobs)}],
    }
    text = json.dumps(document, separators=(',', ':')).encode()
    text += b' ' * (-len(text) % 4)
    binary = b''.join(blobs)
    body = (struct.pack('<I4s', len(text), b'JSON') + text
            + struct.pack('<I4s', len(binary), b'BIN\x00') + binary)
    put('glb', 'skinned_animated.glb', struct.pack('<4sII', b'glTF', 2, 12 + len(body)) + body)


def safetensors_bytes(tensors, metadata=None):
    """A safetensors file: the 8-byte header length, the JSON header, the data."""
    header = {'__metadata__': metadata} if metadata else {}
    data = b''
    for name, (dtype, shape, raw) in tensors.items():
        header[name] = {'dtype': dtype, 'shape': shape,
                        'data_offsets': [len(data), len(data) + len(raw)]}
        data += raw
    text = json.dumps(header, separators=(',', ':')).encode()
    text += b' ' * (-len(text) % 8)
    return struct.pack('<Q', len(text)) + text + data


def checkpoints():
    """Plain tensors; and checkpoints whose metadata configures a model, one refused for its
    sizes (the tensors hold too little), one with room for every parameter (a padding tensor
    under `model.`) that gets as far as matching the parameters."""
    put('checkpoint', 'plain.safetensors', safetensors_bytes({
        'a': ('F32', [2, 3], np.arange(6, dtype='<f4').tobytes()),
        'b': ('F16', [4], np.ones(4, dtype='<f2').tobytes()),
        'c': ('I64', [0, 3], b''),
    }))
    config = {'joints': 52, 'latent': 32, 'layers': 2, 'heads': 2, 'feed_forward': 64,
              'fusion_layers': 1, 'dropout': 0.0, 'prefix_frames': 4, 'predicted_frames': 8,
              'text_embedding': 16, 'bps_points': 1024, 'object_representation': 'hand_relative',
              'stream_layout': 'dual', 'body_fusion': 'network',
              'prediction': 'prefix_residual_world'}
    metadata = lambda config: {'dex2hoi.format': 'dex2hoi-checkpoint-1',
                               'dex2hoi.model_config': json.dumps(config)}
    put('checkpoint', 'tiny_config.safetensors', safetensors_bytes(
        {'model.x': ('F32', [2], np.zeros(2, '<f4').tobytes())}, metadata(config)))
    small = dict(config, joints=2, latent=2, layers=1, heads=1, feed_forward=2, prefix_frames=1,
                 predicted_frames=1, text_embedding=1, bps_points=1, prediction='absolute')
    put('checkpoint', 'small_config.safetensors', safetensors_bytes(
        {'model.pad': ('U8', [4096], bytes(4096))}, metadata(small)))


def yamls():
    """What PyYAML's `yaml.dump` writes for HUMOTO's text files: plain, quoted, folded and
    block scalars, nested values skipped."""
    put('yaml', 'scalars.yaml', b"""# a comment
long_script: The person walks to the table, picks up the mug with the right hand and
  puts it on the shelf.
objects:
- mug
- shelf
nested:
  key: value
quoted: 'It''s a: test'
double: "line one\\nline two"
short_script: pick up the mug  # trailing comment
block: |
  first
  second
folded: >-
  one
  two
---
""")


if __name__ == '__main__':
    pickles()
    npys()
    meshes()
    glb()
    checkpoints()
    yamls()
    sys.exit(0)
