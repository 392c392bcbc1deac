#!/usr/bin/env bash
# The GPU checks of dex2hoi, run on a machine with an NVIDIA GPU and the driver, from the
# repository root, with `target/cuda-pack/` made by `cargo xtask build-cuda` carried along.
# Each phase has a time limit and goes on when one fails; logs and figures go to
# $OUT/gpu-check.tar.gz (default OUT=/tmp/gpu-check) and the picture of a 300-frame sample
# beside it. The whole script fits one 10-minute call.
#   1. the machine: GPU, driver, and that the binary finds every CUDA library (those of the
#      machine's PyTorch wheels, `site-packages/nvidia/*/lib`, which this script puts on
#      LD_LIBRARY_PATH);
#   2. the CUDA tests (forward of every model variant, a training step, the surface search,
#      the fused optimiser, a checkpoint written on the GPU sampled on both devices);
#   3. the profile of a `small` training step (scripts/cuda-profile.c through CUPTI): kernels,
#      copies and driver calls per step and the GPU's busy time against the wall time, from
#      runs of 10 and 40 steps, with the fused optimiser and with the tensor-operation one
#      (profile.txt);
#   4. `small` trained on the procedural dataset for a fixed time, with each optimiser, and
#      `paper` (with the built-in text encoder) with the fused one: median step time and its
#      parts (steps.txt);
#   5. a one-window sample (40 frames after the 20-frame prefix, 50 DDIM steps, guidance) on
#      each device, timed, and 300 frames on the GPU;
#   6. the PyTorch reference (bench/torch_reference.py) on the same GPU: `small` eager, in
#      inference mode and compiled, with its training step; `paper`'s sampling;
#   7. the ratios: dex2hoi's training step and window against PyTorch's, 300 frames against
#      real time, GPU memory (ratios.txt).
# Phase limits in seconds: GPU_CHECK_{TESTS,PROFILE,TRAIN,TORCH,COMPILE}_SECONDS (COMPILE 0: no
# `torch.compile`). It took about 4 minutes
# without `torch.compile`; compiling adds up to 3. For a dry run
# elsewhere: GPU_CHECK_PACK (a folder of gzipped binaries), GPU_CHECK_DEVICE (default cuda).
set -uo pipefail

OUT=${OUT:-/tmp/gpu-check}
mkdir -p "$OUT"
BIN=/tmp/dex2hoi-gpu
WORK=/tmp/dex2hoi-work
rm -rf "$WORK"
mkdir -p "$BIN" "$WORK"
PACK=${GPU_CHECK_PACK:-target/cuda-pack}
DEVICE=${GPU_CHECK_DEVICE:-cuda}
SEQUENCES=${GPU_CHECK_SEQUENCES:-500}
TRAIN_SECONDS=${GPU_CHECK_TRAIN_SECONDS:-70}

phase() { echo; echo "=== $* ($(date +%T))"; }
# Stack traces and warnings off the log.
quiet() { grep -v "^ *[0-9]*: \|^ *at \|warning\|^Stack backtrace:\|^$"; }

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
ldd "$BIN/libdex2hoi-profile.so" 2>/dev/null | grep cupti
if ldd "$BIN/dex2hoi" | grep -q 'not found'; then
    echo "missing libraries: the binary cannot start"
fi

phase "CUDA tests"
if [[ -x $BIN/dex2hoi-train-cuda ]]; then
    timeout "${GPU_CHECK_TESTS_SECONDS:-120}" "$BIN/dex2hoi-train-cuda" --test-threads=1 \
        --nocapture >"$OUT/tests.log" 2>&1
    grep -E "^test |test result|panicked|: value " "$OUT/tests.log"
fi

phase "procedural dataset ($SEQUENCES sequences)"
timeout 60 "$BIN/dex2hoi" data synth --out "$WORK/synth" --sequences "$SEQUENCES" --seed 0 |
    tail -1

# Every step logged, so that the step times and their parts can be read; `composite` is the
# same run with AdamW and the EMA as tensor operations.
sed 's/^log_every = .*/log_every = 1/' configs/small.toml >"$WORK/fused.toml"
sed '/^\[optimizer\]/a fused = false' "$WORK/fused.toml" >"$WORK/composite.toml"
# `paper` with the built-in text encoder: CLIP's weights are not on the machine.
python3 - configs/paper.toml configs/small.toml >"$WORK/paper.toml" <<'PY'
import re, sys
paper, small = (open(f).read() for f in sys.argv[1:])
text = re.search(r"^\[text\]\n.*?(?=^\[)", small, re.M | re.S).group(0)
paper = re.sub(r"^\[text\]\n.*?(?=^\[)", lambda _: text, paper, flags=re.M | re.S)
print(re.sub(r"^log_every = .*$", "log_every = 1", paper, flags=re.M), end="")
PY

train() { # NAME CONFIG SECONDS STEPS [ENV...]: one run, stopped by Ctrl-C after SECONDS
    local name=$1 config=$2 seconds=$3 steps=$4
    shift 4
    env "$@" timeout --foreground -s INT "$seconds" "$BIN/dex2hoi" train --config "$config" \
        --data "$WORK/synth" --out "$WORK/$name" --steps "$steps" --device "$DEVICE" 2>&1 |
        quiet | tail -2
}

phase "profile: small, 10 and 40 steps, each optimiser"
for variant in fused composite; do
    for steps in 10 40; do
        train "profile-$variant-$steps" "$WORK/$variant.toml" \
            "${GPU_CHECK_PROFILE_SECONDS:-35}" "$steps" \
            CUDA_INJECTION64_PATH="$BIN/libdex2hoi-profile.so" \
            DEX2HOI_PROFILE_OUT="$OUT/profile-$variant-$steps.json"
    done
done
python3 - "$OUT" <<'PY' | tee "$OUT/profile.txt"
import json, sys
from pathlib import Path
out = Path(sys.argv[1])
for variant in ["fused", "composite"]:
    try:
        short, long = (json.loads((out / f"profile-{variant}-{n}.json").read_text()) for n in (10, 40))
    except (OSError, ValueError) as e:
        print(f"{variant}: no profile ({e})")
        continue
    per = lambda key: (long[key] - short[key]) / 30
    calls = {k: (long["driver_calls"].get(k, 0) - short["driver_calls"].get(k, 0)) / 30
             for k in long["driver_calls"]}
    top = sorted(calls.items(), key=lambda kv: -kv[1])[:8]
    print(f"{variant}: per step (40 - 10 steps, profiled): {per('kernels'):.0f} kernels, "
          f"{per('copies_host_to_device'):.0f} uploads, {per('copies_device_to_host'):.0f} "
          f"reads back, {per('fills'):.0f} fills; GPU busy {per('busy_s') * 1e3:.1f} ms "
          f"(kernels {per('kernel_s') * 1e3:.1f} ms) of {per('wall_s') * 1e3:.1f} ms wall; "
          f"dropped records {long['dropped_records']}")
    print("  driver calls per step: " + ", ".join(f"{k} {v:.0f}" for k, v in top))
    print("  kernels by time (40-step run): " + "; ".join(
        f"{name[:60]} x{count} {seconds * 1e3:.0f} ms" for name, count, seconds in long["top_kernels"][:6]))
PY

phase "train small ($TRAIN_SECONDS s), then with the tensor-operation optimiser, then paper"
# The GPU's memory in use, every half second (the CUDA context's included).
nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -lms 500 >"$WORK/memory.txt" 2>/dev/null &
watcher=$!
train run-gpu "$WORK/fused.toml" "$TRAIN_SECONDS" 100000
kill "$watcher" 2>/dev/null
MEMORY=$(sort -n "$WORK/memory.txt" | tail -1)
echo "GPU memory in use while training small, at most: $MEMORY MiB"
train run-composite "$WORK/composite.toml" $((TRAIN_SECONDS / 2)) 100000
train run-paper "$WORK/paper.toml" $((TRAIN_SECONDS / 2)) 100000
cp "$WORK/run-gpu/metrics.jsonl" "$OUT/metrics-gpu.jsonl"
python3 - "$WORK" "$OUT" "${MEMORY:-0}" <<'PY' | tee "$OUT/steps.txt"
import json, statistics, sys
from pathlib import Path
summary = {"memory_mib": int(sys.argv[3] or 0)}
for name in ["run-gpu", "run-composite", "run-paper"]:
    try:
        rows = [json.loads(l) for l in (Path(sys.argv[1]) / name / "metrics.jsonl").read_text().splitlines()]
    except OSError as e:
        print(f"{name}: no metrics ({e})")
        continue
    rows = [r for r in rows if r.get("timing")][10:]  # the first steps warm up
    if not rows:
        print(f"{name}: too few steps")
        continue
    median = lambda f: statistics.median(f(r) for r in rows)
    parts = ", ".join(f"{k} {median(lambda r: r['timing'][k]) * 1e3:.1f} ms" for k in rows[0]["timing"])
    print(f"{name}: {len(rows)} steps after 10, median {median(lambda r: r['seconds']) * 1e3:.1f} ms "
          f"({parts}); last loss {rows[-1]['loss']:.4f}")
    summary[name] = {"steps": len(rows), "median_s": median(lambda r: r["seconds"])}
(Path(sys.argv[2]) / "steps.json").write_text(json.dumps(summary))
PY

phase "one-window samples"
for device in "$DEVICE" "$DEVICE" cpu; do
    /usr/bin/time -f "$device: %e s wall, %M KiB peak resident" "$BIN/dex2hoi" sample \
        --run "$WORK/run-gpu" --device "$device" --text "The person picks up the mug." \
        --object mug --frames 40 --out "$WORK/sample-$device" 2>&1 | quiet |
        grep "generated\|wall" | sed "s/^generated/$device: generated/" | tee -a "$OUT/sampling.txt"
done
"$BIN/dex2hoi" sample --run "$WORK/run-gpu" --device "$DEVICE" --text "The person picks up the mug." \
    --object mug --frames 300 --out "$WORK/sample-300" 2>&1 | grep "generated" | tee -a "$OUT/sampling.txt"
cp "$WORK/sample-300/preview.png" "$OUT/sample-300-gpu.png" 2>/dev/null

phase "PyTorch reference on the GPU"
# One preset per call: a call stopped at its limit writes nothing. `small` also compiled.
COMPILE_SECONDS=${GPU_CHECK_COMPILE_SECONDS:-180}
if [[ $COMPILE_SECONDS == 0 ]]; then compile=(--no-compile); else compile=(--compile-timeout "$COMPILE_SECONDS"); fi
timeout "${GPU_CHECK_TORCH_SECONDS:-240}" python3 bench/torch_reference.py --device cuda \
    --presets small --skip-check "${compile[@]}" --out "$OUT/torch-small.json" 2>&1 | tail -12
timeout 75 python3 bench/torch_reference.py --device cuda --presets paper --skip-check \
    --no-compile --no-train --out "$OUT/torch-paper.json" 2>&1 | tail -8

phase "ratios"
python3 - "$OUT" <<'PY' | tee "$OUT/ratios.txt"
import json, re, sys
from pathlib import Path
out = Path(sys.argv[1])
def read(name):
    try:
        return json.loads((out / name).read_text())
    except (OSError, ValueError):
        return None
steps, torch = read("steps.json") or {}, read("torch-small.json") or {}
ours = steps.get("run-gpu", {}).get("median_s")
theirs = torch.get("train_small", {}).get("seconds")
if ours and theirs:
    print(f"training step, small: dex2hoi {ours * 1e3:.1f} ms, PyTorch eager {theirs * 1e3:.1f} ms "
          f"(L_diff only): dex2hoi at {theirs / ours:.2f}x PyTorch's speed")
sampling = (out / "sampling.txt").read_text() if (out / "sampling.txt").exists() else ""
windows = [float(m) for m in re.findall(r"cuda\S*: generated 40 frames .* in ([0-9.]+) s", sampling)]
sample = torch.get("small", {}).get("sample", {})
if windows:
    window = windows[-1]
    for mode in ["eager", "inference_mode", "compile"]:
        seconds = (sample.get(mode) or {}).get("seconds")
        if seconds:
            print(f"one window, small: dex2hoi {window:.3f} s, PyTorch {mode} {seconds:.3f} s: "
                  f"dex2hoi at {seconds / window:.2f}x")
long = re.search(r"generated 300 frames .* ([0-9.]+)x real time", sampling)
if long:
    print(f"300 frames: {long.group(1)}x real time")
memory = steps.get("memory_mib")
peak = torch.get("train_small", {}).get("peak_gpu_gib")
if memory and peak:
    print(f"GPU memory training small: dex2hoi {memory} MiB in use (context included), "
          f"PyTorch {peak * 1024:.0f} MiB allocated (tensors only)")
PY

# The device machine sends back at most 8 files: the logs and figures in one archive.
(cd "$OUT" && tar czf gpu-check.tar.gz --remove-files -- *.log *.json *.jsonl *.txt 2>/dev/null)
ls "$OUT"

phase done
