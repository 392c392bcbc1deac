#!/usr/bin/env bash
# Whether a model takes the hand and the side from the words: the mug in the middle of the
# table (so its place tells neither), pick and place with each hand to each side and inspect
# with each hand, 200 frames from the standing start, seeds 1 and 2; then, per sample, which
# wrist stays by the mug while it is lifted and where it ends (scripts/hand-words.py).
#
#   scripts/hand-words.sh MODEL OUT_DIR      # MODEL: a packed model file or a run directory
#
# DEX2HOI (default target/release/dex2hoi) is the binary. Samples already in OUT_DIR are kept.
set -uo pipefail
if (($# != 2)); then
    sed -n '2,9p' "$0" >&2
    exit 2
fi
BIN=${DEX2HOI:-target/release/dex2hoi}
MODEL=$1
OUT=$2
mkdir -p "$OUT"
# NAME|PROMPT (the name: task, hand, side)
PROMPTS=(
    "pick-L-left|The person picks up the mug with the left hand and puts it down to the left."
    "pick-R-left|The person picks up the mug with the right hand and puts it down to the left."
    "pick-L-right|The person picks up the mug with the left hand and puts it down to the right."
    "pick-R-right|The person picks up the mug with the right hand and puts it down to the right."
    "inspect-L-back|The person picks up the mug with the left hand, turns it to look at it and puts it back."
    "inspect-R-back|The person picks up the mug with the right hand, turns it to look at it and puts it back."
)
status=0
for entry in "${PROMPTS[@]}"; do
    IFS='|' read -r name text <<<"$entry"
    for seed in 1 2; do
        [[ -f $OUT/$name-$seed/motion.npz ]] && continue
        "$BIN" sample --run "$MODEL" --text "$text" --object mug@0,0.955,0.39 --frames 200 \
            --seed "$seed" --out "$OUT/$name-$seed" >/dev/null ||
            { echo "$OUT/$name-$seed: sampling failed" >&2; status=1; }
    done
done
python3 "$(dirname "$0")/hand-words.py" "$OUT" || status=1
exit $status
