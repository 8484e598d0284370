#!/usr/bin/env python3
"""The bindings' overhead: the same cones traced through the Rust API (tools/src/bin/cones_bench.rs),
the C ABI (ctypes on target/release/libaggtool_capi.so) and the Python module (a wheel built by
maturin --release), best of --repeat runs each, as cones per second and as ratios.

    cargo build --release -p aggtool-tools --bin cones_bench && cargo build --release -p aggtool-capi
    (cd integrations/python && maturin build --release -o /tmp/aggwheel)
    pip install --target /tmp/aggsite /tmp/aggwheel/aggtool-*.whl
    PYTHONPATH=/tmp/aggsite python3 benches/bindings.py FILE.agg [--cones 262144] [--repeat 5]
"""
import argparse
import ctypes
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


class AggCone(ctypes.Structure):
    _fields_ = [("origin", ctypes.c_float * 3), ("dir", ctypes.c_float * 3), ("aperture", ctypes.c_float)]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("agg")
    ap.add_argument("--cones", type=int, default=1 << 18)
    ap.add_argument("--repeat", type=int, default=5)
    a = ap.parse_args()
    import aggtool

    scene = aggtool.open(a.agg)
    lo, hi = map(np.asarray, scene.bounds)
    centre, r = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo)
    rng = np.random.default_rng(1)
    # Cones from a camera 2.5 radii away, aimed at points of the bounding box: a 512² image's
    # worth of pixel cones.
    eye = (centre + np.array([0.3, 0.35, 1.0]) / np.linalg.norm([0.3, 0.35, 1.0]) * 2.5 * r).astype(np.float32)
    targets = lo + rng.random((a.cones, 3)) * (hi - lo)
    d = (targets - eye).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.broadcast_to(eye, d.shape).astype(np.float32).copy()
    aperture = np.float32(2 * np.tan(np.radians(20)) / 512)

    def best(f):
        t = []
        for _ in range(a.repeat):
            s = time.perf_counter()
            out = f()
            t.append(time.perf_counter() - s)
        return min(t), out

    t_py, out_py = best(lambda: scene.trace(o, d, float(aperture), aggtool.Lights(), seed=1))

    lib = ctypes.CDLL(str(ROOT / "target" / "release" / "libaggtool_capi.so"))
    lib.agg_open.restype = ctypes.c_void_p
    lib.agg_lights_new.restype = ctypes.c_void_p
    lib.agg_trace_cones.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_size_t,
                                    ctypes.c_uint64, ctypes.c_void_p]
    s = lib.agg_open(a.agg.encode())
    lights = lib.agg_lights_new()
    cones = np.zeros((a.cones, 7), np.float32)
    cones[:, 0:3], cones[:, 3:6], cones[:, 6] = o, d, aperture
    rgba = np.zeros((a.cones, 4), np.float32)

    def c_call():
        code = lib.agg_trace_cones(s, lights, cones.ctypes.data, a.cones, 1, rgba.ctypes.data)
        assert code == 0
        return rgba
    t_c, out_c = best(c_call)
    assert np.array_equal(out_c, out_py), "C ABI and Python traced different values"

    with tempfile.TemporaryDirectory() as tmp:
        f = Path(tmp) / "cones.f32"
        cones.astype("<f4").tofile(f)
        exe = ROOT / "target" / "release" / "cones_bench"
        line = subprocess.run([str(exe), a.agg, str(f), "--repeat", str(a.repeat)],
                              capture_output=True, text=True, check=True).stdout.strip()
    t_rust = float(line.split(" in ")[1].split(" s")[0])
    n = a.cones / 1e6
    print(line)
    print(f"C ABI: {t_c:.4f} s, {n / t_c:.3f} M cones/s, {t_c / t_rust:.3f}x the Rust API's time")
    print(f"Python: {t_py:.4f} s, {n / t_py:.3f} M cones/s, {t_py / t_rust:.3f}x the Rust API's time")


if __name__ == "__main__":
    main()
