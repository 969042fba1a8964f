"""Time the COLMAP readers on a synthetic 300-image model (100k points, track length 5, 1500
observations per image), binary and text:  python bench/colmap_load_speed.py /tmp/m300"""
import shutil
import struct
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing
from l3d_app.data.colmap_model import read_model

if len(sys.argv) != 2:  # one line and exit 2, as main.py's usage errors
    print(f"usage: python bench/colmap_load_speed.py OUT_DIR", file=sys.stderr)
    sys.exit(2)
root = Path(sys.argv[1])
sp = root / "sparse/0"
sp.mkdir(parents=True, exist_ok=True)
N, P, OBS = 300, 100_000, 1500
rng = np.random.default_rng(0)
with open(sp / "cameras.bin", "wb") as f:
    f.write(struct.pack("<Q", 1) + struct.pack("<iiQQ", 1, 1, 1600, 1200) + struct.pack("<4d", 1000, 1000, 800, 600))
obs_dt = np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")])
with open(sp / "images.bin", "wb") as f:
    f.write(struct.pack("<Q", N))
    for i in range(N):
        f.write(struct.pack("<i7di", i + 1, 1, 0, 0, 0, 0, 0, 3, 1) + f"im{i:04d}.jpg".encode() + b"\0"
                + struct.pack("<Q", OBS))
        o = np.zeros(OBS, obs_dt)
        o["x"], o["y"], o["id"] = rng.random(OBS) * 1600, rng.random(OBS) * 1200, rng.integers(1, P, OBS)
        f.write(o.tobytes())
rec = np.dtype([("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("err", "<f8"), ("len", "<u8"), ("track", "<i4", 10)])
r = np.zeros(P, rec)
r["id"], r["xyz"], r["rgb"], r["len"] = np.arange(1, P + 1), rng.normal(size=(P, 3)), rng.integers(0, 255, (P, 3)), 5
with open(sp / "points3D.bin", "wb") as f:
    f.write(struct.pack("<Q", P) + r.tobytes())
tx = root / "text" / "sparse" / "0"
tx.mkdir(parents=True, exist_ok=True)
(tx / "cameras.txt").write_text("1 PINHOLE 1600 1200 1000 1000 800 600\n")
with open(tx / "images.txt", "w") as f:
    for i in range(N):
        obs = " ".join(f"{x:.2f} {y:.2f} {k}" for x, y, k in zip(rng.random(OBS) * 1600, rng.random(OBS) * 1200,
                                                                 rng.integers(1, P, OBS)))
        f.write(f"{i + 1} 1 0 0 0 0 0 3 1 im{i:04d}.jpg\n{obs}\n")
with open(tx / "points3D.txt", "w") as f:
    for k in range(P):
        x = r["xyz"][k]
        f.write(f"{k + 1} {x[0]:.6f} {x[1]:.6f} {x[2]:.6f} 10 20 30 0.5 1 2 3 4 5 6 7 8 9 10\n")
for name, folder in (("binary", sp), ("text", tx)):
    t = time.perf_counter()
    m = read_model(folder)
    print(f"{name}: {time.perf_counter() - t:.2f} s for {len(m.names)} images, {len(m.points)} points")
