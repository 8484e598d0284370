#!/usr/bin/env bash
# What the boundary-visibility ray budget costs: bakes ASSET at --max-res RES three times, with
# a ray per ABV cell on the finest level (--abv-full-res RES), per 2×2 cells (RES/2) and per
# 4×4 cells (RES/4), renders the finest level (--level RES, RES² pixels, 64 spp) under a sun and
# a blue sky, and prints each bake's time, the finest level's size and ABV seconds, and the
# RMSE against the reference renderer at 1024 spp. Work files go to a temporary folder.
#
#   cargo build --release && benches/abv-budget.sh [ASSET] [RES]
set -euo pipefail
cd "$(dirname "$0")/.."
bin=$PWD/target/release/aggtool
asset=$(realpath "${1:-../shared/assets/sh3d_chandelier_scopia/chandelier-lamp.obj}")
res=${2:-128}
[ -x "$bin" ] || { echo "build first: cargo build --release" >&2; exit 1; }
[ -f "$asset" ] || { echo "skipped: $asset is absent" >&2; exit 0; }
tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
cd "$tmp"
"$bin" reference "$asset" --auto-view --width "$res" --height "$res" --spp 1 --save-view auto.json -o auto.exr >/dev/null
python3 - <<'PY'
import json
v = json.load(open("auto.json"))
v["sun"] = {"direction": [0.4, 1.0, 0.3], "irradiance": 3.0}
v["environment"] = {"constant": [0.3, 0.4, 0.6]}
json.dump(v, open("view.json", "w"))
PY
"$bin" reference "$asset" --view view.json --spp 1024 -o ref.exr >/dev/null
echo "| ABV rays | bake wall s | bake CPU s | ${res}³ level MiB | ${res}³ ABV s | RMSE |"
echo "|---|---|---|---|---|---|"
for full in "$res" $((res / 2)) $((res / 4)); do
  /usr/bin/time -f "%e %U %S" -o t "$bin" convert "$asset" -o b.agg --max-res "$res" --abv-full-res "$full" --report r.json >/dev/null 2>&1
  "$bin" render b.agg --view view.json --level "$res" --spp 64 -o r.exr >/dev/null
  rmse=$("$bin" compare r.exr ref.exr --json | python3 -c "import json,sys; print(round(json.load(sys.stdin)['rmse'], 6))")
  python3 - "$full" "$res" "$rmse" <<'PY'
import json, sys
full, res, rmse = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
wall, u, s = map(float, open("t").read().split()[-3:])
l = json.load(open("r.json"))["levels"][0]
print(f"| {l['abv_rays_per_face']} per face | {wall:.1f} | {u + s:.0f} | {l['bytes'] / 2**20:.2f} | {l['seconds']['faces']:.1f} | {rmse} |")
PY
done
