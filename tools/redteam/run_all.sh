#!/bin/sh
# Every class of the red team, then the table README quotes. From the
# repository's root, after `cargo build --release`:
#   tools/redteam/run_all.sh
# IRID (the binary, default target/release/irid) and REDTEAM_OUT (default
# /tmp/irid-redteam) may be set. Needs python3 with numpy and PyYAML.
set -eu
here=$(dirname "$0")
out=${REDTEAM_OUT:-/tmp/irid-redteam}
mkdir -p "$out"
rm -f "$out/results.jsonl"
for c in c1_basic c1_thin c1_thin_var c2_mismatch c2b_interlayer_readme c3_calib c4_nonrefl; do
  python3 "$here/$c.py" > "$out/$c.log"
done
python3 "$here/tally.py"
