#!/usr/bin/env bash
# Trains several runs side by side on one GPU for a fixed time and sends their snapshots back
# as packed models, for the training studies of docs/results/. Run on a machine
# with an NVIDIA GPU from the repository root, with `target/cuda-pack/` made by
# `cargo xtask build-cuda` carried along:
#
#   scripts/gpu-train.sh SECONDS NAME=CONFIG[:KEEP] ...
#
# Each run trains CONFIG (a training configuration file) on the procedural dataset of
# docs/results/ (`data synth --sequences 2000 --seed 0`, made here; the same files as
# /work/runs/synth-2000) with a snapshot every 1000 steps, until SECONDS have passed; then it
# is stopped with Ctrl-C (its checkpoint is written). The device machine sends back at most 8
# files of 16 MiB, so each run's snapshots are packed (`model pack --f16`, EMA weights only:
# what `evaluate --run` and `sample --run` read) and tarred in groups under 16 MiB; KEEP
# (default: all) keeps only the last KEEP snapshots. Logs and metrics.jsonl go to
# $OUT/logs.tar.gz. The runs share the GPU and the host's cores.
#
# Continuing a run: GPU_TRAIN_RESUME=DIR (a run folder carried along: checkpoint.safetensors,
# config.toml, dataset.json, stats.json, metrics.jsonl) starts every run from a copy of it with
# `train --resume` and the run's own step count (GPU_TRAIN_STEPS sets another). A CONFIG that
# differs from DIR/config.toml in some settings (a loss weight, the batch size; comments and
# blank lines aside, the same lines in the same order) has those lines
# changed in its copy's checkpoint too (scripts/retarget-checkpoint.py): a continuation under
# another setting, no longer a bit-exact resume. GPU_TRAIN_CHECKPOINTS="NAME ..." sends those
# runs' checkpoints back in parts under 16 MiB (`cat NAME-checkpoint.part* >
# checkpoint.safetensors`), so that they can be continued elsewhere.
#
# Fine-tuning a trained model: GPU_TRAIN_INIT_FROM=MODEL (a packed model carried along, such as
# the shipped one) starts every run from its EMA weights (`train --init-from`) under its CONFIG,
# with GPU_TRAIN_STEPS steps (default 100000).
#
# GPU_TRAIN_SEED (default 0) is the procedural dataset's seed (the shipped model's last
# training phase used `--sequences 8000 --seed 1`). GPU_TRAIN_LAST_F32=1 packs each run's last
# kept snapshot in f32 (the EMA weights exactly, as shipped) and the others in f16. The
# training ends early when every run has finished its steps.
#
# For a dry run elsewhere: GPU_TRAIN_PACK (a folder of gzipped binaries), GPU_TRAIN_DEVICE,
# GPU_TRAIN_SEQUENCES, GPU_TRAIN_DATA (an existing dataset instead of making one).
set -uo pipefail
if [[ -n ${GPU_TRAIN_RESUME:-} && -n ${GPU_TRAIN_INIT_FROM:-} ]]; then
    echo "GPU_TRAIN_RESUME and GPU_TRAIN_INIT_FROM: one or the other" >&2
    exit 2
fi
if [[ -n ${GPU_TRAIN_INIT_FROM:-} && ! -f $GPU_TRAIN_INIT_FROM ]]; then
    echo "GPU_TRAIN_INIT_FROM=$GPU_TRAIN_INIT_FROM: expected a packed model file" >&2
    exit 2
fi

OUT=${OUT:-/tmp/gpu-train}
SECONDS_TO_TRAIN=$1
shift
mkdir -p "$OUT"
BIN=/tmp/dex2hoi-gpu
WORK=/tmp/dex2hoi-train
mkdir -p "$BIN" "$WORK/logs"
LIMIT=$((15 * 1024 * 1024))

phase() { echo; echo "=== $* ($(date +%T))"; }

phase unpack
for f in "${GPU_TRAIN_PACK:-target/cuda-pack}"/*.gz; do
    gunzip -c "$f" >"$BIN/$(basename "$f" .gz)" && chmod +x "$BIN/$(basename "$f" .gz)"
done
CUDA_LIBS=$(python3 -c '
import glob, os
try:
    import nvidia
except ImportError:
    raise SystemExit
print(":".join(sorted({os.path.dirname(f) for base in nvidia.__path__
    for f in glob.glob(os.path.join(base, "**", "lib", "lib*.so*"), recursive=True)})))')
export LD_LIBRARY_PATH="$CUDA_LIBS${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null

DATA=${GPU_TRAIN_DATA:-$WORK/synth}
if [[ -z ${GPU_TRAIN_DATA:-} ]]; then
    phase "procedural dataset"
    "$BIN/dex2hoi" data synth --out "$DATA" --sequences "${GPU_TRAIN_SEQUENCES:-2000}" \
        --seed "${GPU_TRAIN_SEED:-0}" |
        tail -1
fi

# Copies the run folder $GPU_TRAIN_RESUME to $1 and makes its checkpoint's stored configuration
# agree with the configuration file $2, line by line.
continue_from() {
    local from=$GPU_TRAIN_RESUME run=$1 config=$2
    mkdir -p "$run"
    cp "$from"/{checkpoint.safetensors,config.toml,dataset.json,stats.json,metrics.jsonl} "$run"/ || return 1
    settings() { grep -Ev '^[[:space:]]*(#|$)' "$1"; }
    if (($(settings "$config" | wc -l) != $(settings "$from/config.toml" | wc -l))); then
        echo "$config: expected the settings of $from/config.toml, some with other values" >&2
        return 1
    fi
    while IFS=$'\t' read -r old new; do
        [[ $old == "$new" || $old == steps\ =* ]] && continue
        python3 scripts/retarget-checkpoint.py "$run/checkpoint.safetensors" "$old" "$new" || return 1
    done < <(paste <(settings "$from/config.toml") <(settings "$config"))
}

phase "training for $SECONDS_TO_TRAIN s"
pids=()
for spec in "$@"; do
    name=${spec%%=*}
    config=${spec#*=}
    config=${config%%:*}
    args=(--config "$config" --data "$DATA" --out "$WORK/$name"
        --snapshot-every "${GPU_TRAIN_SNAPSHOT_EVERY:-1000}" --device "${GPU_TRAIN_DEVICE:-cuda}")
    log=$WORK/logs/$name.log
    : >"$log"
    [[ -n ${GPU_TRAIN_INIT_FROM:-} ]] && args+=(--init-from "$GPU_TRAIN_INIT_FROM")
    if [[ -n ${GPU_TRAIN_RESUME:-} ]]; then
        continue_from "$WORK/$name" "$config" >>"$log" 2>&1 || {
            cat "$log"
            continue
        }
        args+=(--resume)
        [[ -n ${GPU_TRAIN_STEPS:-} ]] && args+=(--steps "$GPU_TRAIN_STEPS")
    else
        args+=(--steps "${GPU_TRAIN_STEPS:-100000}")
    fi
    "$BIN/dex2hoi" train "${args[@]}" >>"$log" 2>&1 &
    pids+=($!)
done
# Until the time is up or every run has finished.
for ((waited = 0; waited < SECONDS_TO_TRAIN; waited += 5)); do
    running=0
    for pid in "${pids[@]}"; do kill -0 "$pid" 2>/dev/null && running=1; done
    ((running)) || break
    sleep 5
done
for pid in "${pids[@]}"; do kill -INT "$pid" 2>/dev/null; done
wait
nvidia-smi --query-gpu=memory.used --format=csv,noheader 2>/dev/null

phase "packing"
for spec in "$@"; do
    name=${spec%%=*}
    keep=all
    [[ $spec == *:* ]] && keep=${spec##*:}
    tail -2 "$WORK/logs/$name.log"
    cp "$WORK/$name/metrics.jsonl" "$WORK/logs/$name-metrics.jsonl" 2>/dev/null
    snapshots=$(ls -d "$WORK/$name"/snapshots/step-* 2>/dev/null | sort)
    [[ $keep != all ]] && snapshots=$(echo "$snapshots" | tail -n "$keep")
    mkdir -p "$WORK/packed/$name"
    last=$(echo "$snapshots" | tail -n 1)
    for snapshot in $snapshots; do
        precision=--f16
        [[ ${GPU_TRAIN_LAST_F32:-} == 1 && $snapshot == "$last" ]] && precision=
        "$BIN/dex2hoi" model pack --run "$snapshot" $precision \
            --out "$WORK/packed/$name/$name-$(basename "$snapshot").safetensors" >/dev/null ||
            echo "could not pack $snapshot"
    done
    # Groups of packed files under the size limit, one tar each.
    group=0
    size=0
    files=()
    flush() {
        if ((${#files[@]})); then
            tar -cf "$OUT/$name-$group.tar" -C "$WORK/packed/$name" "${files[@]}"
            # One model larger than the limit travels in parts (`cat NAME.tar.part* > NAME.tar`).
            if (($(stat -c %s "$OUT/$name-$group.tar") > LIMIT)); then
                split -b "$LIMIT" -d "$OUT/$name-$group.tar" "$OUT/$name-$group.tar.part"
                rm "$OUT/$name-$group.tar"
            fi
            group=$((group + 1))
        fi
        files=()
        size=0
    }
    for f in $(ls "$WORK/packed/$name" 2>/dev/null | sort); do
        bytes=$(stat -c %s "$WORK/packed/$name/$f")
        ((size + bytes > LIMIT)) && flush
        files+=("$f")
        size=$((size + bytes))
    done
    flush
done
for name in ${GPU_TRAIN_CHECKPOINTS:-}; do
    split -b "$LIMIT" -d "$WORK/$name/checkpoint.safetensors" "$OUT/$name-checkpoint.part" ||
        echo "could not send back the checkpoint of $name"
done
tar -czf "$OUT/logs.tar.gz" -C "$WORK" logs
ls -la "$OUT"
phase done
