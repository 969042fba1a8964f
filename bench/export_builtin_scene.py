"""Export the built-in scene (64 px, its 112 cameras, 3000 coloured surface samples) as a COLMAP folder
(binary and text) and as a NeRF-synthetic folder with the SAME train/val/test images as data=colmap's
split (test = every 8th by name, val = every 8th of the rest).

    python bench/export_builtin_scene.py OUT_DIR
    python main.py task=gs_train data=colmap data.root=OUT_DIR/colmap_bin time_budget=150 iters=3000 threads=1
    python main.py task=gs_train data=blender data.root=OUT_DIR/blender time_budget=150 iters=3000 threads=1
"""
import json, sys
from pathlib import Path
import torch, imageio.v2 as imageio, numpy as np
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without installing
from l3d_app.data.nerf_views import nerf_builtin, nerf_scene
from l3d_app.data.colmap_export import write_colmap
from l3d_app.data.captures import split_by_name
from l3d_app.geometry.cameras import to_opengl_c2w
from l3d_app.geometry.sampling import sample_points_on_mesh
if len(sys.argv) != 2:  # one line and exit 2, as main.py's usage errors
    print(f"usage: python bench/export_builtin_scene.py OUT_DIR", file=sys.stderr)
    sys.exit(2)
out = Path(sys.argv[1])
d = nerf_builtin(cache_dir=str(out / "cache"))
pc = sample_points_on_mesh(nerf_scene(), 3000, torch.Generator().manual_seed(0), return_colors=True)
names = [f"{i:05d}.png" for i in range(len(d.images))]
write_colmap(out / "colmap_bin", d.cameras, d.images, pc.points, pc.colors, names=names, binary=True)
write_colmap(out / "colmap_txt", d.cameras, d.images, pc.points, pc.colors, names=names, binary=False)
tr, va, te = split_by_name(names, 8, 8)
c2w = to_opengl_c2w(d.cameras.to(dtype=torch.float64))
W = d.cameras.width
fov_x = float(2 * torch.atan(W / 2 / d.cameras.fx[0].double()))
bl = out / "blender"
for split, idx in (("train", tr), ("val", va), ("test", te)):
    (bl / split).mkdir(parents=True, exist_ok=True)
    frames = []
    for i in idx.tolist():
        imageio.imwrite(bl / split / names[i], (d.images[i].numpy() * 255 + 0.5).astype(np.uint8))
        frames.append({"file_path": f"./{split}/{names[i][:-4]}", "transform_matrix": c2w[i].tolist()})
    (bl / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": fov_x, "frames": frames}))
print(len(tr), len(va), len(te))
