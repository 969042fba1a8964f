"""Which points a set of cameras actually observes, given the true surface.

Multi-view reconstruction cannot recover surface that no input camera sees (the underside
of an object on its stand, the inside of a joint). Benchmarks therefore score against the
*observed* part (the DTU evaluation does it with its observation masks). Here a point
counts as observed when at least one camera sees it: it projects inside that camera's image,
in front of the camera, and no farther than the true surface's depth at that pixel plus a
tolerance; and, when the point's surface normal is given (points sampled on the true
surface), the surface faces that camera. The true depth maps are an input, rendered by the caller
(:func:`l3d_app.render.mesh.rgbd.true_depth_maps`, our own rasteriser at ``scale`` times the
cameras' resolution: finer pixels, so a smaller tolerance suffices on thin parts and
silhouettes); metrics never render.
The facing test matters at grazing views: from a camera a little above the underside's
plane, the whole underside projects onto a one-pixel sliver along the bottom edge, where a
depth lookup alone is ambiguous.

The same test applies to points of a *reconstruction*: a reconstructed point in free space
in front of the true surface is observed (it is a visible floater and counts as an error);
one hidden behind the true surface in every view (e.g. a guess under the stand) is not.
The test itself lives in :mod:`l3d_app.geometry.visibility` (extracted meshes are culled with
it too); this module is the metrics' name for it.
"""

from __future__ import annotations

from l3d_app.geometry.visibility import observed_mask

__all__ = ["observed_mask"]
