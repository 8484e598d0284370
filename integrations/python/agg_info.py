#!/usr/bin/env python3
"""Print an .agg file's header and level table using only the schema's generated Python code
(flatc --python, committed beside this script) and the `flatbuffers` package: the proof that
the format can be read without aggtool.

    python3 integrations/python/agg_info.py FILE.agg [--json]
"""
import json
import os
import struct
import sys
import zlib

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from aggtool.format.Index import Index  # noqa: E402  (generated)

MAGIC = b"\x89AGG\r\n\x1a\n"
MAJOR = 1
HEADER = struct.Struct("<8sHHIQQQII12sI")  # 64 bytes, see schema/aggregate.fbs


class AggError(Exception):
    pass


def read_header(data):
    if data[: min(len(data), 8)] != MAGIC[: min(len(data), 8)]:
        raise AggError("not an .agg file (wrong identifier)")
    if len(data) < HEADER.size:
        raise AggError(f"truncated: {len(data)} bytes")
    (magic, major, minor, hsize, ix_off, ix_size, fsize, ix_crc, _flags, _res, hcrc) = HEADER.unpack_from(data)
    if major != MAJOR:
        raise AggError(f"format version {major}.x is not supported (this reader reads {MAJOR}.x)")
    if zlib.crc32(data[:60]) != hcrc:
        raise AggError("corrupt: header checksum mismatch")
    if len(data) != fsize:
        raise AggError(f"{'truncated' if len(data) < fsize else 'trailing data'}: header says {fsize} bytes, file has {len(data)}")
    index = data[ix_off: ix_off + ix_size]
    if zlib.crc32(index) != ix_crc:
        raise AggError("corrupt: index checksum mismatch")
    if index[4:8] != b"AGGI":
        raise AggError("corrupt: index has the wrong identifier")
    return {"major": major, "minor": minor, "bytes": fsize, "index_offset": ix_off, "index_size": ix_size}, index


def describe(path):
    with open(path, "rb") as f:
        data = f.read()
    header, index_bytes = read_header(data)
    ix = Index.GetRootAs(index_bytes, 0)
    s = ix.Settings()
    levels = []
    for i in range(ix.LevelsLength()):
        lv = ix.Levels(i)
        c = lv.Counts()
        blocks = [lv.VoxelBlocks(j) for j in range(lv.VoxelBlocksLength())]
        fblocks = [lv.FaceBlocks(j) for j in range(lv.FaceBlocksLength())]
        levels.append({
            "res": lv.Res(),
            "voxels": c.Voxels() if c else sum(b.Count() for b in blocks),
            "faces": c.Faces() if c else sum(b.Count() for b in fblocks),
            "voxel_blocks": len(blocks),
            "face_blocks": len(fblocks),
            "bytes": sum(b.Size() for b in blocks + fblocks),
        })
    return {
        "file": path,
        "format": f"{header['major']}.{header['minor']}",
        "bytes": header["bytes"],
        "generator": (ix.Generator() or b"").decode(),
        "source": (ix.Source() or b"").decode(),
        "max_res": s.MaxRes(),
        "aiv_res": s.AivRes(),
        "abv_res": s.AbvRes(),
        "abv_full_res": s.AbvFullRes(),
        # 1.4: the float layout kept (--lossless); older files are float whatever it says.
        "lossless": s.Lossless() if header["minor"] >= 4 else True,
        # 1.5: the Zstandard level of the blocks (0: stored as FlatBuffers).
        "compression": s.Compression() if header["minor"] >= 5 else 0,
        # 1.7: levels finer than this are visibility levels, reading this level's AIV (0: none).
        "shading_res": s.ShadingRes() if header["minor"] >= 7 else 0,
        "effects_kept": ix.EffectsKept(),
        "tables_version": ix.TablesVersion(),
        "levels": levels,
    }


def main(argv):
    if len(argv) < 2 or argv[1] in ("-h", "--help"):
        print(__doc__.strip())
        return 2
    try:
        d = describe(argv[1])
    except (OSError, AggError) as e:
        print(f"error: {argv[1]}: {e}", file=sys.stderr)
        return 1
    if "--json" in argv:
        print(json.dumps(d, indent=2))
        return 0
    print(f"{d['file']}: aggtool format {d['format']}, {d['bytes']} bytes, written by {d['generator']}")
    layout = "float" if d["lossless"] else "quantized (1.4)"
    if d["compression"]:
        layout += f", blocks zstd level {d['compression']} (1.5; in byte planes from 1.6, derived fields left out from 1.8)"
    print(f"source: {d['source']}; max-res {d['max_res']}, AIV {d['aiv_res']}², ABV {d['abv_res']}²; effects 0x{d['effects_kept']:x}; tables v{d['tables_version']}; layout {layout}")
    if d["shading_res"] and d["shading_res"] < d["max_res"]:
        print(f"visibility levels (1.7): finer than {d['shading_res']}³, reading its voxels' AIV")
    print(f"{'level':>6} {'voxels':>10} {'faces':>10} {'vblocks':>7} {'fblocks':>7} {'bytes':>12}")
    for l in d["levels"]:
        print(f"{l['res']:>5}³ {l['voxels']:>10} {l['faces']:>10} {l['voxel_blocks']:>7} {l['face_blocks']:>7} {l['bytes']:>12}")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main(sys.argv))
    except BrokenPipeError:
        # The reader of our output went away (`agg_info.py F.agg | head`): stop quietly.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        sys.exit(1)
