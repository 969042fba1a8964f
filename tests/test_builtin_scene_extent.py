"""The built-in scene's bounding box (the denominator of volsdf's ``chamfer_rel_diag``) derived
from its construction in data/nerf_views.py ``nerf_scene``, not copied from an output.

* x, z: the plinth, a box of size 1.2 centred on the y axis: +-0.6 (the poles at +-0.5 with
  radius 0.03, the ring and the sphere stay inside);
* y min: the plinth's underside, -0.55 - 0.25 / 2 = -0.675;
* y max: the tilted ring's top. A torus with axis n (unit), centre c, radii R, r reaches
  ``c_y + R sqrt(1 - n_y^2) + r``. Its axis is Y turned by Rz(20) Rx(60) (``euler_xyz``:
  x first): ``Rx(60) e_y = (0, cos 60, sin 60)``, then Rz(20) gives
  ``n_y = cos 20 cos 60``. The mesh has 48 x 8 vertices, so its top vertex lies below the
  smooth torus's by at most ``R (1 - cos(pi / 48)) + r (1 - cos(pi / 8))``.
"""

from __future__ import annotations

import math

import numpy as np

from l3d_app.data.nerf_views import nerf_scene


def test_builtin_scene_bounding_box_matches_its_construction():
    v = nerf_scene().verts.double().numpy()
    lo, hi = v.min(0), v.max(0)
    np.testing.assert_allclose([lo[0], hi[0], lo[2], hi[2]], [-0.6, 0.6, -0.6, 0.6], atol=1e-6)
    assert abs(lo[1] - (-0.55 - 0.125)) < 1e-6
    R, r = 0.45, 0.025
    n_y = math.cos(math.radians(20)) * math.cos(math.radians(60))
    top = 0.2 + R * math.sqrt(1 - n_y ** 2) + r
    slack = R * (1 - math.cos(math.pi / 48)) + r * (1 - math.cos(math.pi / 8))
    assert top - slack - 1e-6 <= hi[1] <= top + 1e-6, (hi[1], top, slack)
    diag = float(np.linalg.norm(hi - lo))
    smooth = math.sqrt(1.2 ** 2 + 1.2 ** 2 + (top + 0.675) ** 2)
    assert smooth - 1e-3 <= diag <= smooth + 1e-6, (diag, smooth)     # 2.1361 smooth, 2.1354 polygonal
