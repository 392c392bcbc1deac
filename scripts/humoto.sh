#!/usr/bin/env bash
# Real motion capture end to end on HUMOTO's public subset (docs/results/humoto.md): prepare it
# (fixed split, the licence kept), train the `humoto` preset (resumed if OUT/run has a
# checkpoint), train an evaluator on the same data, evaluate (the paper's protocol and the
# long one), sample every test sequence's scene and script and a few prompts of our own on the
# HUMOTO character, and pack the model with its licence.
#
#   scripts/humoto.sh HUMOTO_GLB_DIR OUT_DIR [STEPS]
#
# HUMOTO_GLB_DIR holds the sequence folders (`<seq>/<seq>.glb`) and animations.json, as
# published; OUT_DIR receives everything (keep it out of the repository: HUMOTO is under the
# Adobe Research License, and so is what is made from it). STEPS overrides the preset's 24000
# (about 1.5 hours of a 2-core CPU). DEX2HOI (default target/release/dex2hoi) is the binary.
# Steps already done (a checkpoint at STEPS, an evaluator, a report, a sample) are kept.
set -euo pipefail
if (($# < 2 || $# > 3)); then
    sed -n '2,14p' "$0" >&2
    exit 2
fi
BIN=${DEX2HOI:-target/release/dex2hoi}
ROOT=$(cd "$(dirname "$0")/.." && pwd)
GLB=$1
OUT=$2
STEPS=${3:-}
mkdir -p "$OUT"
steps_args=()
[[ -n $STEPS ]] && steps_args=(--steps "$STEPS")

[[ -f $OUT/data/manifest.json ]] ||
    "$BIN" data prepare --format humoto --root "$GLB" --out "$OUT/data"

if [[ -f $OUT/run/checkpoint.safetensors ]]; then
    "$BIN" train --resume --data "$OUT/data" --out "$OUT/run" "${steps_args[@]}"
else
    "$BIN" train --config "$ROOT/configs/humoto.toml" --data "$OUT/data" --out "$OUT/run" \
        "${steps_args[@]}"
fi

[[ -f $OUT/evaluator/evaluator.safetensors ]] ||
    "$BIN" evaluator train --data "$OUT/data" --out "$OUT/evaluator"
[[ -f $OUT/report/report.md ]] ||
    "$BIN" evaluate --run "$OUT/run" --data "$OUT/data" --evaluator "$OUT/evaluator" \
        --out "$OUT/report" --long

# The character every sample wears: the one inside the public GLBs.
character=$(find "$GLB" -name '*.glb' | sort | head -n 1)
# Each test sequence from its first frame: its objects where they stand, its script, its length.
python3 - "$OUT/data/test.json" >"$OUT/test-ids.txt" <<'EOF'
import json, sys
for s in json.load(open(sys.argv[1])):
    print(s["source_id"].rsplit("/", 1)[-1])
EOF
while read -r id; do
    [[ -f $OUT/samples/$id/motion.npz ]] ||
        "$BIN" sample --run "$OUT/run" --data "$OUT/data" --sequence "$id" --character "$character" \
            --free-objects as-generated --out "$OUT/samples/$id"
done <"$OUT/test-ids.txt"
# Prompts of our own with the data's objects, 10 s each.
PROMPTS=(
    "lift-board|The subject lifts the cutting board with both hands and examines it.|cutting_board@0,0.9,0.4"
    "carry-vase|The subject carries the vase with the right hand and walks forward.|vase@-0.2,0.9,0.35"
    "drag-table|The subject drags the side table and walks backward.|side_table@0,0.3,0.6"
)
for entry in "${PROMPTS[@]}"; do
    IFS='|' read -r name text object <<<"$entry"
    [[ -f $OUT/samples/$name/motion.npz ]] ||
        "$BIN" sample --run "$OUT/run" --data "$OUT/data" --object "$object" --text "$text" \
            --frames 200 --seed 1 --character "$character" --free-objects as-generated \
            --out "$OUT/samples/$name"
done
"$BIN" model pack --run "$OUT/run" --out "$OUT/humoto.safetensors"
"$BIN" model info --run "$OUT/humoto.safetensors"
