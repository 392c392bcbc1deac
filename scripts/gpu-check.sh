#!/usr/bin/env bash
# The GPU checks of dex2hoi, run on a machine with an NVIDIA GPU and the driver, from the
# repository root, with `target/cuda-pack/` made by `cargo xtask build-cuda` carried along.
# Each phase has a time limit and goes on when one fails; logs and figures go to $OUT
# (default /tmp/gpu-check):
#   1. the machine: GPU, driver, and that the binary finds every CUDA library (those of the
#      machine's PyTorch wheels, `site-packages/nvidia/*/lib`, which this script puts on
#      LD_LIBRARY_PATH);
#   2. the CUDA tests (forward of every model variant, a training step, a checkpoint written
#      on the GPU sampled on both devices);
#   3. `small` trained on the procedural dataset on the GPU, then the same run on the CPU for
#      its first steps (loss curves to compare: metrics-gpu.jsonl, metrics-cpu.jsonl);
#   4. a one-window sample (40 frames after the 20-frame prefix, 50 DDIM steps, guidance) on
#      each device, timed;
#   5. the PyTorch reference (bench/torch_reference.py) on the same GPU.
# Phase limits in seconds can be set with GPU_CHECK_{TESTS,TRAIN,CPU_TRAIN,TORCH}_SECONDS.
set -uo pipefail

OUT=${OUT:-/tmp/gpu-check}
mkdir -p "$OUT"
BIN=/tmp/dex2hoi-gpu
WORK=/tmp/dex2hoi-work
mkdir -p "$BIN" "$WORK"
PACK=target/cuda-pack
SEQUENCES=${GPU_CHECK_SEQUENCES:-500}

phase() { echo; echo "=== $* ($(date +%T))"; }

phase unpack
for f in "$PACK"/*.gz; do
    gunzip -c "$f" >"$BIN/$(basename "$f" .gz)" && chmod +x "$BIN/$(basename "$f" .gz)"
done
ls -la "$BIN"

phase machine
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
CUDA_LIBS=$(python3 - <<'PY'
import glob, os
dirs = set()
try:
    import nvidia
    for base in nvidia.__path__:
        for f in glob.glob(os.path.join(base, "**", "lib", "lib*.so*"), recursive=True):
            dirs.add(os.path.dirname(f))
except ImportError:
    pass
print(":".join(sorted(dirs)))
PY
)
export LD_LIBRARY_PATH="$CUDA_LIBS${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
ldd "$BIN/dex2hoi" | grep -E 'cuda|nvrtc|curand|cublas'
if ldd "$BIN/dex2hoi" | grep -q 'not found'; then
    echo "missing libraries: the binary cannot start"
fi

phase "CUDA tests"
timeout "${GPU_CHECK_TESTS_SECONDS:-120}" "$BIN/dex2hoi-train-cuda" --test-threads=1 2>&1 |
    tee "$OUT/tests.log"

phase "procedural dataset ($SEQUENCES sequences)"
timeout 120 "$BIN/dex2hoi" data synth --out "$WORK/synth" --sequences "$SEQUENCES" --seed 0 |
    tail -2

# Every step logged, so the two devices' curves can be compared step by step.
sed 's/^log_every = .*/log_every = 1/' configs/small.toml >"$WORK/small.toml"

phase "train small on the GPU"
timeout --foreground -s INT "${GPU_CHECK_TRAIN_SECONDS:-300}" "$BIN/dex2hoi" train --config "$WORK/small.toml" \
    --data "$WORK/synth" --out "$WORK/run-gpu" --steps 5000 --device cuda 2>&1 | grep -v "^ *[0-9]*: \|^ *at " | tail -8
cp "$WORK/run-gpu/metrics.jsonl" "$OUT/metrics-gpu.jsonl"
cp "$WORK/run-gpu/loss.png" "$OUT/loss-gpu.png" 2>/dev/null
nvidia-smi --query-gpu=memory.used --format=csv,noheader

phase "train small on the CPU ($(nproc) cores), the same run's first steps"
timeout --foreground -s INT "${GPU_CHECK_CPU_TRAIN_SECONDS:-30}" "$BIN/dex2hoi" train --config "$WORK/small.toml" \
    --data "$WORK/synth" --out "$WORK/run-cpu" --steps 5000 --device cpu 2>&1 | grep -v "^ *[0-9]*: \|^ *at " | tail -4
cp "$WORK/run-cpu/metrics.jsonl" "$OUT/metrics-cpu.jsonl"

phase "one-window samples"
for device in cuda cuda cpu; do
    /usr/bin/time -f "$device: %e s wall, %M KiB peak resident" "$BIN/dex2hoi" sample \
        --run "$WORK/run-gpu" --device "$device" --text "The person picks up the mug." \
        --object mug --frames 40 --out "$WORK/sample-$device" 2>&1 | grep -v "^ *[0-9]*: \|^ *at \|warning" | tail -4
done
"$BIN/dex2hoi" sample --run "$WORK/run-gpu" --device cuda --text "The person picks up the mug." \
    --object mug --frames 300 --out "$WORK/sample-300" 2>&1 | grep "generated"
cp "$WORK/sample-cuda/preview.png" "$OUT/sample-gpu.png" 2>/dev/null
cp "$WORK/sample-300/preview.gif" "$OUT/sample-300-gpu.gif" 2>/dev/null

phase "PyTorch reference on the GPU"
timeout "${GPU_CHECK_TORCH_SECONDS:-90}" python3 bench/torch_reference.py --device cuda \
    --presets small --skip-check --no-compile --out "$OUT/torch-gpu.json" 2>&1 | tail -30

phase done
