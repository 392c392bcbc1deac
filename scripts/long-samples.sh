#!/usr/bin/env bash
# 160-frame samples of one prompt per procedural task family, seeds 0-5 (48 samples), for the
# long-generation figures of docs/results/shipped-model.md (objects sinking into the table,
# untouched objects drifting). Read them with scripts/long-samples.py.
#
#   scripts/long-samples.sh MODEL OUT_DIR      # MODEL: a packed model file or a run directory
#
# DEX2HOI (default target/release/dex2hoi) is the binary; SAMPLE_ARGS (split at spaces) are
# passed to every `sample`, e.g. "--guidance 2.5". Samples already in OUT_DIR are kept.
set -uo pipefail
if (($# != 2)); then
    sed -n '2,9p' "$0" >&2
    exit 2
fi
BIN=${DEX2HOI:-target/release/dex2hoi}
MODEL=$1
OUT=$2
mkdir -p "$OUT"
# NAME|PROMPT|OBJECTS (unplaced: on the table in front, two side by side, the first on the left)
PROMPTS=(
    "pick|Using the right hand, someone lifts the mug and sets it down a little to the left.|mug"
    "inspect|A person lifts the mug with the left hand, examines it from several sides and sets it down.|mug"
    "both|The person lifts the bowl with both hands and puts it back down.|bowl"
    "handover|A person lifts the bottle with the right hand, gives it to the other hand and places it to the left.|bottle"
    "holdtwo|Someone lifts the bottle in the left hand and the can in the right hand at the same time and sets them down again.|bottle can"
    "pour|A person lifts the bottle with the right hand, tips it over the bowl and puts it back.|bowl bottle"
    "swap|The person swaps the places of the mug and the can.|mug can"
    "nextto|The person moves the can next to the bowl with the right hand.|bowl can"
)
status=0
for entry in "${PROMPTS[@]}"; do
    IFS='|' read -r name text objects <<<"$entry"
    object_args=()
    for object in $objects; do object_args+=(--object "$object"); done
    for seed in 0 1 2 3 4 5; do
        [[ -f $OUT/$name-$seed/motion.npz ]] && continue
        "$BIN" sample --run "$MODEL" --text "$text" "${object_args[@]}" --frames 160 \
            --seed "$seed" ${SAMPLE_ARGS:-} --out "$OUT/$name-$seed" >/dev/null ||
            { echo "$OUT/$name-$seed: sampling failed" >&2; status=1; }
    done
done
exit $status
