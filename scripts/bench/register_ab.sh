#!/usr/bin/env bash
# Register stage, before/after: runs two vispack-register builds on the same phantom folders,
# interleaved (A B A B ...), --threads 1 --force, each in its own copy of the folder; prints
# the median CPU seconds (user + sys) per slice, peak RSS, whether the two transforms.json
# are byte-identical, and vispack-score's drift RMS for each.
# Usage: scripts/bench/register_ab.sh REGISTER_A REGISTER_B SCORE_EXE REPS PHANTOM_DIR...
set -euo pipefail
a=$1 b=$2 score=$3 reps=$4
shift 4
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
for dir in "$@"; do
  name=$(basename "$dir")
  n=$(python3 -c "import json,sys; print(len(json.load(open('$dir/truth/transforms.json'))['slices']))" 2>/dev/null || echo 0)
  for v in A B; do rm -rf "$tmp/$v"; cp -r "$dir" "$tmp/$v"; rm -rf "$tmp/$v/work"; done
  for ((i = 0; i < reps; ++i)); do
    for v in A B; do
      exe=$a; [[ $v == B ]] && exe=$b
      /usr/bin/time -f "%U %S %M" -o "$tmp/$v.time" "$exe" --config "$tmp/$v/config.json" \
        --force --threads 1 --quiet
      cat "$tmp/$v.time" >>"$tmp/$v.times"
    done
  done
  same=no
  cmp -s "$tmp/A/work/register/transforms.json" "$tmp/B/work/register/transforms.json" && same=yes
  for v in A B; do
    cpu=$(awk '{print $1 + $2}' "$tmp/$v.times" | sort -g | awk '{a[NR]=$1} END {print a[int((NR+1)/2)]}')
    rss=$(awk '{print $3}' "$tmp/$v.times" | sort -g | tail -1)
    rms=$("$score" --truth "$tmp/$v/truth" --work "$tmp/$v/work" --json |
      python3 -c "import json,sys; d=json.load(sys.stdin)['drift']; print(round(d['rms_px'],4), round(d['relative_rms_px'],4))")
    echo "$name $v slices=$n cpu_s=$cpu cpu_s_per_slice=$(python3 -c "print(round($cpu/max($n,1),3))") peak_rss_kb=$rss drift_rms_px,relative_rms_px=${rms/ /,} transforms_identical=$same"
  done
  rm -f "$tmp"/*.times
done
