#!/usr/bin/env bash
# The compression study (issue 16): for every asset under ../shared/assets (or those given after
# `--`), one bake at RES in the uncompressed layout (`--lossless --compression-level 0`: format
# 1.3's floats), rewritten by tools/src/bin/requantize.rs into format 1.4's quantized layout (stored
# uncompressed) and into 1.5's (quantized, blocks compressed at the default level); prints a
# Markdown table of bytes (file and finest level), the ratios, the seconds the rewriting took
# (the compression's share of a bake), the asset's geometry bytes (`aggtool info --json`:
# each mesh once, 32 B a vertex, 12 a triangle) and, with RENDER=1, the RMSE of the lossless and
# the compressed aggregate against a 1024-spp reference at RES² pixels (256 spp each, same seed:
# the difference is what compression changes).
#
#   cargo build --release -p aggtool -p aggtool-tools --bin aggtool --bin requantize && benches/compression-study.sh RES [-- ASSET ...]
#
# Bakes go to $KEEP (kept) or a temporary folder (removed).
set -euo pipefail
cd "$(dirname "$0")/.."
bin=target/release/aggtool
rq=target/release/requantize
assets=../shared/assets
[ -x "$bin" ] && [ -x "$rq" ] || { echo "build first: cargo build --release -p aggtool -p aggtool-tools --bin aggtool --bin requantize" >&2; exit 1; }
[ -d "$assets" ] || { echo "skipped: $assets is absent" >&2; exit 0; }
res=${1:-64}; shift || true
picked=()
if [ "${1:-}" = "--" ]; then shift; picked=("$@"); fi
list_assets() {
  if [ ${#picked[@]} -gt 0 ]; then printf '%s\n' "${picked[@]}"
  else find "$assets" \( -name '*.obj' -o -name '*.glb' -o -name '*.gltf' \) | sort; fi
}
if [ -n "${KEEP:-}" ]; then tmp=$KEEP; mkdir -p "$tmp"; else tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT; fi
echo "| asset | res | geometry MB | 1.3 MB | 1.4 MB | 1.5 MB | 1.5 finest level MB | 1.3/1.5 | 1.4/1.5 | smaller than mesh | bake CPU s | rewrite s | RMSE 1.3 | RMSE 1.5 |"
echo "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"
list_assets | while read -r a; do
  name=$(basename "$a"); base="$tmp/${name%.*}-$res"
  if ! /usr/bin/time -f "%U %S" -o "$base.cpu" "$bin" convert "$a" -o "$base-13.agg" --max-res "$res" \
      --lossless --compression-level 0 >"$base.log" 2>&1; then
    echo "| $name | ${res}³ | FAILED: $(tail -1 "$base.log") |||||||||||||"; continue
  fi
  "$rq" "$base-13.agg" "$base-14.agg" --bytes-only --compression-level 0 >/dev/null
  start=$(date +%s.%N)
  "$rq" "$base-13.agg" "$base-15.agg" --bytes-only >/dev/null
  end=$(date +%s.%N)
  "$bin" info --json "$a" >"$base.info.json"
  "$bin" inspect --json "$base-15.agg" >"$base.inspect.json"
  r13=""; r15=""
  if [ "${RENDER:-0}" = 1 ]; then
    "$bin" reference "$a" --auto-view --width "$res" --height "$res" --spp 1024 --save-view "$base.view.json" -o "$base-ref.exr" >/dev/null 2>&1
    "$bin" render "$base-13.agg" --view "$base.view.json" --spp 256 -o "$base-13.exr" >/dev/null 2>&1
    "$bin" render "$base-15.agg" --view "$base.view.json" --spp 256 -o "$base-15.exr" >/dev/null 2>&1
    r13=$("$bin" compare "$base-13.exr" "$base-ref.exr" | awk '{print $2}')
    r15=$("$bin" compare "$base-15.exr" "$base-ref.exr" | awk '{print $2}')
  fi
  python3 - "$name" "$res" "$base" "$start" "$end" "$r13" "$r15" <<'PY'
import json, os, sys
name, res, base, start, end, r13, r15 = sys.argv[1:]
size = lambda p: os.path.getsize(p) / 1e6
info = json.load(open(base + ".info.json"))
ins = json.load(open(base + ".inspect.json"))
u, s = open(base + ".cpu").read().split()[-2:]
geo = info["geometry_bytes"] / 1e6
b13, b14, b15 = size(base + "-13.agg"), size(base + "-14.agg"), size(base + "-15.agg")
finest = ins["levels"][0]["bytes"] / 1e6
print(f"| {name} | {res}³ | {geo:.2f} | {b13:.2f} | {b14:.2f} | {b15:.2f} | {finest:.2f} | {b13 / b15:.2f}× | {b14 / b15:.2f}× | "
      f"{'yes' if b15 < geo else 'no'} | {float(u) + float(s):.0f} | {float(end) - float(start):.1f} | {r13} | {r15} |")
PY
  [ -n "${KEEP:-}" ] || rm -f "$base"-1[345].agg
done
