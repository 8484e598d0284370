#!/usr/bin/env python3
"""The clustered-PCA curve (issue 16, paper Table 4's "1 CPCA Rep." row): for each aggregate,
tools/src/bin/cpca_probe.rs over clusters × representatives, the bytes per map of CPCA (8-bit
weights, fixed-point representative trees) against its RMS error per map cell, beside the
bytes of the stored trees (float, and format 1.4's 6-byte nodes: 6/20 of the float bytes).
Writes table.md and, where matplotlib is installed, cpca_curve.png.

    cargo build --release -p aggtool-tools --bin cpca_probe
    python3 benches/cpca_curve.py A-13.agg [B-13.agg ...] -o DIR      # runs the probe
    python3 benches/cpca_curve.py --from probe-output.txt -o DIR      # parses a saved run

Give it float (1.3, `--lossless`) files: the stored bytes it reports are then the floats'.
"""
import argparse
import re
import subprocess
import sys
from pathlib import Path

GRID = [(c, ra, rb) for c in (10, 30, 120) for ra, rb in ((1, 1), (4, 4), (10, 16), (20, 60))]
LINE = re.compile(r"(AIV|ABV): (\d+) maps \d+², stored (\d+) B \(([\d.]+) B/map\); CPCA ~(\d+) B "
                  r"\(([\d.]+) B/map, [\d.]+x\);.* ([\d.]+) reps/cluster; RMS error ([\d.]+)")
HEAD = re.compile(r"== (\S+) clusters (\d+) reps (\d+) (\d+)")


def parse(text):
    rows, cur = [], None
    for line in text.splitlines():
        if m := HEAD.match(line):
            cur = (m[1], int(m[2]), int(m[3]), int(m[4]))
        elif (m := LINE.match(line)) and cur:
            rows.append(dict(file=cur[0], clusters=cur[1], max_reps=cur[2] if m[1] == "AIV" else cur[3],
                             map=m[1], stored=float(m[4]), cpca=float(m[6]), reps=float(m[7]),
                             error=float(m[8])))
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("aggs", nargs="*")
    ap.add_argument("--from", dest="source")
    ap.add_argument("-o", "--output", default="cpca-curve")
    a = ap.parse_args()
    if a.source:
        text = Path(a.source).read_text()
    else:
        probe = Path(__file__).resolve().parents[1] / "target/release/cpca_probe"
        out = []
        for f in a.aggs:
            for c, ra, rb in GRID:
                r = subprocess.run([str(probe), f, str(c), str(ra), str(rb), "0"],
                                   capture_output=True, text=True, check=True)
                out.append(f"== {Path(f).name} clusters {c} reps {ra} {rb}\n{r.stdout}")
        text = "".join(out)
    rows = parse(text)
    if not rows:
        sys.exit("no probe output parsed")
    d = Path(a.output)
    d.mkdir(parents=True, exist_ok=True)
    lines = ["| file | map | clusters | max reps | reps/cluster | CPCA B/map | RMS error | "
             "float trees B/map | 1.4 trees B/map | CPCA vs 1.4 |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        q = r["stored"] * 6 / 20
        lines.append(f"| {r['file']} | {r['map']} | {r['clusters']} | {r['max_reps']} | {r['reps']:.2f} | "
                     f"{r['cpca']:.1f} | {r['error']:.4f} | {r['stored']:.1f} | {q:.1f} | {q / r['cpca']:.2f}× |")
    (d / "table.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed: table only", file=sys.stderr)
        return
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, kind in zip(axes, ("AIV", "ABV")):
        for f in sorted({r["file"] for r in rows}):
            sel = [r for r in rows if r["file"] == f and r["map"] == kind]
            for c in sorted({r["clusters"] for r in sel}):
                pts = sorted((r["error"], r["cpca"]) for r in sel if r["clusters"] == c)
                ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=f"{f} CPCA, {c} clusters")
            s = sel[0]["stored"]
            ax.axhline(s * 6 / 20, ls="--", lw=1, color="k")
            ax.text(0.0, s * 6 / 20, f" 1.4 trees ({f})", va="bottom", fontsize=7)
        ax.set_xscale("symlog", linthresh=1e-3)
        ax.set_xlim(left=0)
        ax.set_xlabel("RMS error per map cell")
        ax.set_ylabel("bytes per map")
        ax.set_title(f"{kind}: CPCA against format 1.4's trees (dashed)")
        ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(d / "cpca_curve.png", dpi=110)
    print(f"output: {d / 'table.md'} and {d / 'cpca_curve.png'}")


if __name__ == "__main__":
    main()
