#!/usr/bin/env bash
# Bakes every asset under ../shared/assets at the given resolutions (default 64 and 256) with
# the release build, one process per bake so that peak memory is per asset, and prints a
# Markdown table: bake seconds (wall, whole command), CPU seconds (user + system: the figure to
# compare when the machine is shared), peak resident memory, .agg size, voxels and faces of the
# finest level. Bakes go to a temporary folder that is removed afterwards.
#
#   cargo build --release && benches/bake-assets.sh [RES ...] [-- ASSET ...]
#
# With `-- ASSET ...` only those assets are baked, in that order. With REPORTS=DIR set, each
# bake's --report JSON (per-stage seconds, bytes per component) is kept there.
set -euo pipefail
cd "$(dirname "$0")/.."
bin=target/release/aggtool
assets=../shared/assets
[ -x "$bin" ] || { echo "build first: cargo build --release" >&2; exit 1; }
[ -d "$assets" ] || { echo "skipped: $assets is absent" >&2; exit 0; }
res_list=(); picked=()
while [ $# -gt 0 ]; do
  if [ "$1" = "--" ]; then shift; picked=("$@"); break; fi
  res_list+=("$1"); shift
done
[ ${#res_list[@]} -gt 0 ] || res_list=(64 256)
list_assets() {
  if [ ${#picked[@]} -gt 0 ]; then printf '%s\n' "${picked[@]}"
  else find "$assets" \( -name '*.obj' -o -name '*.glb' -o -name '*.gltf' \) | sort; fi
}
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
echo "| asset | res | seconds | CPU s | peak MiB | .agg MiB | voxels | faces |"
echo "|---|---|---|---|---|---|---|---|"
for res in "${res_list[@]}"; do
  list_assets | while read -r a; do
    name=$(basename "$a"); out="$tmp/$name.agg"
    start=$(date +%s.%N)
    if /usr/bin/time -f "%U %S %M" -o "$tmp/mem" "$bin" convert "$a" -o "$out" --max-res "$res" --report "$tmp/r.json" >"$tmp/log" 2>&1; then
      end=$(date +%s.%N)
      python3 - "$name" "$res" "$start" "$end" "$tmp/mem" "$tmp/r.json" <<'PY'
import json, sys
name, res, start, end, mem, rep = sys.argv[1:]
r = json.load(open(rep))
u, s, kb = open(mem).read().split()[-3:]
cpu, kb = float(u) + float(s), int(kb)
l = r["levels"][0]
print(f"| {name} | {res}³ | {float(end) - float(start):.1f} | {cpu:.0f} | {kb / 1024:.0f} | {r['bytes'] / 2**20:.1f} | {l['voxels']} | {l['faces']} |")
PY
    else
      echo "| $name | ${res}³ | FAILED: $(tail -1 "$tmp/log") | | | | | |"
    fi
    [ -z "${REPORTS:-}" ] || { mkdir -p "$REPORTS"; cp "$tmp/r.json" "$REPORTS/$name-$res.json" 2>/dev/null || true; }
    rm -f "$out"
  done
done
