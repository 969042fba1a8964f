"""Soft, differentiable mesh rasterisation (SoftRasterizer, Liu et al. 2019) in pure PyTorch.

Conventions are those of :mod:`l3d_app.geometry.cameras` (OpenCV camera frame, pixel
``(row i, col j)`` centred at ``(u, v) = (j + .5, i + .5)``) and of
:class:`~l3d_app.geometry.mesh.Mesh` (UV ``v`` up, texture stored top row first).

Model, per view and pixel centre ``p`` and per face ``j``:

* ``d_j``: distance from ``p`` to the projected triangle, in **NDC units**: pixel distances
  times ``2 / min(H, W)`` (the smaller image side spans [-1, 1], as in PyTorch3D/SoftRas);
  ``d_j = 0`` inside.  The signed squared distance ``x_j = +d_j^2`` inside, ``-d_j^2``
  outside, where "inside" is the distance to the triangle's BOUNDARY.
* coverage probability ``D_j = sigmoid(x_j / sigma)``, ``sigma`` in NDC^2 (0.5 on an edge);
* silhouette ``S = 1 - prod_j (1 - D_j)``, computed as ``-expm1(sum_j logsigmoid(-x_j/sigma))``
  (exact, stable, no clamping needed);
* colour ``I = (sum_j w_j C_j + w_b C_b) / (sum_j w_j + w_b)`` with
  ``w_j = D_j exp(zn_j / gamma)``, ``w_b = exp(background_eps / gamma)`` and normalised
  inverse depth ``zn_j = (far - z_j) / (far - near)`` (1 at the near plane, 0 at the far
  plane; the background sits at ``background_eps``, just in front of the far plane).  It
  is evaluated as a log-sum-exp: ``log w_j = logsigmoid(x_j/sigma) + zn_j/gamma``, minus a
  per-pixel running maximum (detached: the softmax does not depend on it), so neither
  tiny ``sigma`` nor tiny ``gamma`` overflows.
* ``z_j`` and the face colour ``C_j`` use the pixel's barycentrics w.r.t. the projected
  triangle, clamped to [0, 1] and renormalised (so pixels outside the triangle take the
  colour of its nearest part), then made perspective-correct.  ``C_j`` comes from
  per-vertex colours, per-face colours, or a bilinear lookup in a UV texture.

Sparsity: a face contributes to a pixel only where ``D_j >= dist_eps``, i.e. inside the
triangle or within ``r = sqrt(sigma * log((1 - dist_eps) / dist_eps))`` NDC units of it
(``r`` in pixels is ``r * min(H, W) / 2``; e.g. sigma=1e-4, dist_eps=1e-4 at 128 px:
1.94 px).  Contributions below ``dist_eps`` are DROPPED exactly (as in SoftRas), which makes
the result a well-defined function, independent of how candidates are enumerated: the
silhouette changes by at most ``dist_eps`` per face, but the COLOUR takes the face's colour
all the way to that radius (``w_j`` dominates ``w_b`` for any non-negligible ``D_j`` when
``gamma`` is small), a property of the SoftRas aggregation, not of the truncation.

Algorithm (no Python loop over faces or pixels): project, cull faces (below), take each
face's integer pixel bounding box expanded by ``r``, enumerate all (face, pixel)
candidate pairs exactly (a ``searchsorted`` over the cumulative per-face pixel counts, so
there is no padding and no bucketing is needed), evaluate them in chunks of at most
``max_pairs`` pairs, and accumulate per pixel with ``index_add`` (sum of log(1 - D)) and an
online softmax (``scatter_reduce('amax')`` for the running maximum, then ``exp`` and
``index_add``), as in flash attention.  Memory: chunking bounds the forward temporaries;
the tensors autograd keeps for backward still grow with the number of pairs (float32:
~0.25 KB per pair for the silhouette, ~0.4 KB with colours; a 1280-face icosphere filling
~40% of a 128x128 image makes ~1e5 pairs) unless ``checkpoint=True``, which recomputes
each chunk in backward and keeps only dense per-pixel accumulators per chunk.

Culling (a culled face contributes nothing, with zero gradient, never NaN):

* faces with ANY vertex at camera depth ``Z < near`` (crossing or behind the near plane
  are dropped whole, never clipped);
* faces whose vertices are all beyond ``far`` (faces straddling ``far`` are kept; their
  far part just gets ``zn < 0``);
* degenerate faces: doubled screen area ``|A2| <= 16 * eps(dtype) * sum |edge|^2``
  (collinear or coincident vertices, in pixel units);
* faces whose expanded bounding box misses the image.

Both windings are rendered (no back-face culling); depth ordering comes from ``gamma``.
"""

from __future__ import annotations

import math
from typing import Dict, Optional, Sequence, Union

import torch
import torch.nn.functional as F
from torch.utils.checkpoint import checkpoint as _checkpoint

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.geometry.mesh import Mesh
from l3d_app.registry import RENDERERS
from l3d_app.geometry.textures import sample_texture_indexed

__all__ = ["soft_rasterize", "influence_radius", "SoftMeshRenderer"]


def influence_radius(sigma: float, dist_eps: float) -> float:
    """Distance (NDC units) beyond which a face's coverage ``D`` is below ``dist_eps``.

    ``sigmoid(-r^2 / sigma) = dist_eps  <=>  r = sqrt(sigma * log((1 - dist_eps) / dist_eps))``.
    Multiply by ``min(H, W) / 2`` for pixels.
    """
    return math.sqrt(sigma * math.log((1.0 - dist_eps) / dist_eps))


def _batched(x: Optional[torch.Tensor], dims: int, name: str, batch: int):
    """Add a leading batch dim to an unbatched tensor; check the batch is 1 or ``batch``."""
    if x is None:
        return None
    if x.dim() == dims:
        x = x[None]
    if x.dim() != dims + 1 or x.shape[0] not in (1, batch):
        raise UserError(f"{name} must have {dims} dims or a leading batch of 1 or {batch}, "
                        f"got {tuple(x.shape)}")
    return x


def _chunk_contrib(tri, zv, px, py, pix, keep_thr, inv_sigma, near, far, gamma,
                   m_run, color_fn, n_pix, want_color):
    """Per-pixel contributions of one chunk of P (face, pixel) candidate pairs.

    Args:
        tri: (P, 3, 2) projected triangle (pixels); zv: (P, 3) vertex depths (>= near).
        px, py: (P,) pixel centre coordinates (pixels); pix: (P,) flat pixel index.
        keep_thr: squared influence radius (pixels^2); inv_sigma: NDC^2 / (pixel^2 * sigma).
        m_run: (N,) detached running per-pixel max of the colour log-weights.
        color_fn: (aw (P, 3) perspective-correct barycentrics) -> (P, 3) colours.

    Returns:
        log1m (N,) sum of log(1 - D); and when ``want_color``: m_new (N,) new running max,
        wsum (N,) sum of exp(logw - m_new) and wcol (N, 3) the colour-weighted sum.
    """
    p = torch.stack([px, py], dim=-1)
    e = tri.roll(-1, dims=1) - tri                              # edge k: v_k -> v_{k+1}
    ap = p[:, None, :] - tri                                    # (P, 3, 2)
    E = e[..., 0] * ap[..., 1] - e[..., 1] * ap[..., 0]         # edge functions (P, 3)
    area2 = E.sum(-1)                                           # doubled signed area (any p)
    inside = ((E * area2[:, None]) >= 0).all(-1)
    ee = (e * e).sum(-1).clamp_min(1e-30)
    t = ((ap * e).sum(-1) / ee).clamp(0.0, 1.0)
    diff = ap - t[..., None] * e
    d2 = (diff * diff).sum(-1).amin(-1)                         # squared distance, pixels^2
    keep = inside | (d2 <= keep_thr)
    x = torch.where(inside, d2, -d2) * inv_sigma               # signed d^2 / sigma
    log1m = torch.where(keep, F.logsigmoid(-x), torch.zeros_like(x))
    log1m_px = torch.zeros(n_pix, dtype=x.dtype, device=x.device).index_add(0, pix, log1m)
    if not want_color:
        return (log1m_px,)

    # barycentrics of vertex k = E_{k+1} / area2 (area2 is bounded away from 0 by culling)
    bary = E.roll(-1, dims=-1) / area2[:, None]
    bary = bary.clamp(0.0, 1.0)
    bary = bary / bary.sum(-1, keepdim=True).clamp_min(1e-12)   # sum >= 1 before; safety
    wz = bary / zv                                              # zv >= near > 0
    zinv = wz.sum(-1)
    aw = wz / zinv[:, None]                                     # perspective-correct weights
    zn = (far - 1.0 / zinv) / (far - near)
    logw = F.logsigmoid(x) + zn / gamma
    logw = torch.where(keep, logw, torch.full_like(logw, -math.inf))
    with torch.no_grad():
        m_new = m_run.scatter_reduce(0, pix, logw, reduce="amax", include_self=True)
    w = torch.exp(logw - m_new[pix])
    col = color_fn(aw)
    wsum = torch.zeros(n_pix, dtype=x.dtype, device=x.device).index_add(0, pix, w)
    wcol = torch.zeros(n_pix, 3, dtype=x.dtype, device=x.device).index_add(0, pix, w[:, None] * col)
    return log1m_px, m_new, wsum, wcol


def soft_rasterize(cams: Cameras, verts: torch.Tensor, faces: torch.Tensor, *,
                   vert_colors: Optional[torch.Tensor] = None,
                   face_colors: Optional[torch.Tensor] = None,
                   texture: Optional[torch.Tensor] = None,
                   verts_uvs: Optional[torch.Tensor] = None,
                   faces_uvs: Optional[torch.Tensor] = None,
                   sigma: float = 1e-4, gamma: float = 1e-4,
                   background: Union[Sequence[float], torch.Tensor] = (0.0, 0.0, 0.0),
                   near: float = 0.1, far: float = 100.0,
                   dist_eps: float = 1e-4, background_eps: float = 1e-3,
                   max_pairs: int = 1 << 20, checkpoint: bool = False
                   ) -> Dict[str, torch.Tensor]:
    """Soft silhouette and colour images of a triangle mesh (see the module docstring).

    Args:
        cams: B cameras sharing one image size H x W (cast to ``verts``' dtype/device).
        verts: (V, 3) or (B, V, 3) world-space vertex positions (world units).
        faces: (F, 3) long vertex indices.
        vert_colors: optional (V, 3) or (B, V, 3) per-vertex RGB, interpolated.
        face_colors: optional (F, 3) or (B, F, 3) per-face RGB, constant per face.
        texture: optional (Ht, Wt, 3) or (B, Ht, Wt, 3) image, top row first, with
            ``verts_uvs`` (T, 2) (v up) and ``faces_uvs`` (F, 3); see :func:`l3d_app.geometry.textures.sample_texture_indexed`.
            At most one colour source may be given; with none, only the silhouette is made.
        sigma: edge sharpness, NDC^2 units (smaller = sharper, ~ (pixel size)^2 is sharp;
            the pixel size in NDC is ``2 / min(H, W)``). SoftRas default 1e-4.
        gamma: depth-softmax temperature, units of normalised depth ``zn`` in [0, 1]
            (smaller = harder z-test). SoftRas default 1e-4.
        background: (3,) RGB behind everything.
        near, far: camera depths (world units) bounding ``zn``; see culling rules.
        dist_eps: contributions with ``D < dist_eps`` are dropped (sets the radius).
        background_eps: the background's normalised inverse depth ``zn``.
        max_pairs: (face, pixel) candidate pairs evaluated at once (bounds memory).
        checkpoint: recompute each chunk in backward (less memory, ~1.5x time).

    Returns:
        dict with ``silhouette`` (B, H, W) in [0, 1] and, when a colour source is given,
        ``image`` (B, H, W, 3).  Differentiable w.r.t. ``verts``, the colours, the texture
        and ``verts_uvs`` (not the camera culling decisions or the candidate sets).
    """
    if not (sigma > 0 and gamma > 0):
        raise UserError(f"sigma and gamma must be > 0, got sigma={sigma}, gamma={gamma}")
    if not (0 < near < far):
        raise UserError(f"need 0 < near < far, got near={near}, far={far}")
    if not (0 < dist_eps < 0.5):
        raise UserError(f"dist_eps must be in (0, 0.5), got {dist_eps}")
    if faces.dim() != 2 or faces.shape[-1] != 3:
        raise UserError(f"faces must be (F, 3), got {tuple(faces.shape)}")
    if verts.dim() not in (2, 3) or verts.shape[-1] != 3:
        raise UserError(f"verts must be (V, 3) or (B, V, 3), got {tuple(verts.shape)}")
    n_sources = sum(x is not None for x in (vert_colors, face_colors, texture))
    if n_sources > 1:
        raise UserError("give at most one of vert_colors, face_colors, texture")
    if texture is not None and (verts_uvs is None or faces_uvs is None):
        raise UserError("a texture needs verts_uvs and faces_uvs")
    if texture is not None and (tuple(faces_uvs.shape) != tuple(faces.shape) or texture.shape[-1] != 3
                                or verts_uvs.shape[-1] != 2):
        raise UserError("texture must be (..., Ht, Wt, 3), verts_uvs (T, 2) and faces_uvs like faces")
    if int(max_pairs) < 1:
        raise UserError(f"max_pairs must be >= 1, got {max_pairs}")
    want_color = n_sources == 1

    dtype, dev = verts.dtype, verts.device
    cams = cams.to(device=dev, dtype=dtype)
    bv, bc = (verts.shape[0] if verts.dim() == 3 else 1), cams.batch_size
    if bv != bc and 1 not in (bv, bc):
        raise UserError(f"cameras ({bc}) and verts ({bv}) batch sizes differ")
    B = max(bv, bc)
    H, W = cams.height, cams.width
    faces = faces.to(device=dev, dtype=torch.long)
    if faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= verts.shape[-2]):
        raise UserError(f"face indices out of range [0, {verts.shape[-2]})")
    nF = faces.shape[0]
    n_pix = B * H * W

    # ---- projection, per-(view, face) setup ---------------------------------------------
    view = cams.world_to_view(verts)
    if view.shape[0] != B:
        view = view.expand(B, -1, -1)
    z = view[..., 2]
    zs = z.clamp_min(near)                       # culled faces only: keeps values finite
    u = view[..., 0] / zs * cams.fx[:, None] + cams.cx[:, None]
    v = view[..., 1] / zs * cams.fy[:, None] + cams.cy[:, None]
    fuv = torch.stack([u, v], -1)[:, faces].reshape(B * nF, 3, 2)   # (B*F, 3, 2) pixels
    fz = z[:, faces].reshape(B * nF, 3)                             # (B*F, 3) depths

    ndc_per_px = 2.0 / min(H, W)
    r_px = influence_radius(sigma, dist_eps) / ndc_per_px
    with torch.no_grad():
        s, zd = fuv.detach(), fz.detach()
        e = s.roll(-1, dims=1) - s
        area2 = e[:, 0, 0] * e[:, 1, 1] - e[:, 0, 1] * e[:, 1, 0]
        scale = (e * e).sum((-1, -2))
        ok = (zd.amin(-1) >= near) & (zd.amin(-1) <= far) & torch.isfinite(s).all(-1).all(-1)
        ok &= area2.abs() > 16 * torch.finfo(dtype).eps * scale
        lo, hi = s.amin(1), s.amax(1)                                   # (B*F, 2)
        x0 = (lo[:, 0] - r_px - 0.5).ceil().clamp(0, W)
        x1 = (hi[:, 0] + r_px - 0.5).floor().clamp(-1, W - 1)
        y0 = (lo[:, 1] - r_px - 0.5).ceil().clamp(0, H)
        y1 = (hi[:, 1] + r_px - 0.5).floor().clamp(-1, H - 1)
        nx = (x1 - x0 + 1).clamp_min(0).long()
        ny = (y1 - y0 + 1).clamp_min(0).long()
        counts = torch.where(ok, nx * ny, torch.zeros_like(nx))
        inst = counts.nonzero().squeeze(1)                              # (N,) live instances
        counts, nx = counts[inst], nx[inst]
        x0, y0 = x0[inst].long(), y0[inst].long()
        cum = counts.cumsum(0)
        total = int(cum[-1]) if inst.numel() else 0
        inst_b = torch.div(inst, nF, rounding_mode="floor")
        inst_f = inst - inst_b * nF

    tri_i, z_i = fuv[inst], fz[inst]
    bgc = torch.as_tensor(background, dtype=dtype, device=dev).reshape(3)

    # ---- colour source -> per-instance data ----------------------------------------------
    col_i = None
    if vert_colors is not None:
        vc = _batched(vert_colors.to(device=dev, dtype=dtype), 2, "vert_colors", B)
        vb = inst_b if vc.shape[0] == B else torch.zeros_like(inst_b)
        col_i = vc[vb[:, None], faces[inst_f]]                              # (N, 3, 3)
    elif face_colors is not None:
        fc = _batched(face_colors.to(device=dev, dtype=dtype), 2, "face_colors", B)
        col_i = fc[inst_b if fc.shape[0] == B else torch.zeros_like(inst_b), inst_f]  # (N, 3)
    elif texture is not None:
        tex = _batched(texture.to(device=dev, dtype=dtype), 3, "texture", B)
        uv_i = verts_uvs.to(device=dev, dtype=dtype)[faces_uvs.to(dev).long()[inst_f]]  # (N, 3, 2)
        tb_i = inst_b if tex.shape[0] == B else torch.zeros_like(inst_b)

    def make_color_fn(pi):
        if vert_colors is not None:
            c = col_i[pi]
            return lambda aw: (aw[..., None] * c).sum(1)
        if face_colors is not None:
            c = col_i[pi]
            return lambda aw: c
        uvp, tb = uv_i[pi], tb_i[pi]
        return lambda aw: sample_texture_indexed(tex, (aw[..., None] * uvp).sum(1), tb)

    # ---- chunked accumulation -------------------------------------------------------------
    log1m = torch.zeros(n_pix, dtype=dtype, device=dev)
    m = torch.full((n_pix,), background_eps / gamma, dtype=dtype, device=dev)
    wsum = torch.ones(n_pix, dtype=dtype, device=dev)               # background weight
    wcol = bgc.expand(n_pix, 3)
    keep_thr = r_px * r_px
    inv_sigma = ndc_per_px * ndc_per_px / sigma
    for start in range(0, total, max_pairs):
        with torch.no_grad():
            p = torch.arange(start, min(start + max_pairs, total), device=dev)
            pi = torch.searchsorted(cum, p, right=True)
            k = p - (cum[pi] - counts[pi])
            dy = torch.div(k, nx[pi], rounding_mode="floor")
            ix, iy = x0[pi] + k - dy * nx[pi], y0[pi] + dy
            pix = (inst_b[pi] * H + iy) * W + ix
            px, py = ix.to(dtype) + 0.5, iy.to(dtype) + 0.5

        def run(tri, zv, m_run, pi=pi, pix=pix, px=px, py=py):
            color_fn = make_color_fn(pi) if want_color else None
            return _chunk_contrib(tri, zv, px, py, pix, keep_thr, inv_sigma, near, far, gamma,
                                  m_run, color_fn, n_pix, want_color)

        args = (tri_i[pi], z_i[pi], m)
        if checkpoint and torch.is_grad_enabled():
            out = _checkpoint(run, *args, use_reentrant=False)
        else:
            out = run(*args)
        log1m = log1m + out[0]
        if want_color:
            m_new, ws, wc = out[1], out[2], out[3]
            rescale = torch.exp(m - m_new)                         # <= 1, constant
            wsum = wsum * rescale + ws
            wcol = wcol * rescale[:, None] + wc
            m = m_new

    if total == 0:  # nothing visible: keep the outputs attached to the inputs (zero grads)
        anchor = sum((x * 0).sum() for x in (verts, vert_colors, face_colors, texture, verts_uvs)
                     if torch.is_tensor(x) and x.requires_grad)
        log1m = log1m + anchor
        wcol = wcol + anchor
    result = {"silhouette": (0.0 - torch.expm1(log1m)).reshape(B, H, W)}  # 0 - : no -0.0
    if want_color:
        result["image"] = (wcol / wsum[:, None]).reshape(B, H, W, 3)
    return result


@RENDERERS.register("soft_mesh")
class SoftMeshRenderer:
    """Soft mesh renderer: :func:`soft_rasterize` with a mesh's own appearance.

    Uses the mesh's texture if it has one, else its vertex colours, else flat grey (0.5).
    Keyword arguments are those of :func:`soft_rasterize` (sigma in NDC^2, gamma in
    normalised depth, background RGB, near/far in world units).
    """

    def __init__(self, sigma: float = 1e-4, gamma: float = 1e-4,
                 background: Sequence[float] = (0.0, 0.0, 0.0), near: float = 0.1,
                 far: float = 100.0, dist_eps: float = 1e-4, max_pairs: int = 1 << 20,
                 checkpoint: bool = False):
        bg = [float(c) for c in background]
        if len(bg) != 3:
            raise UserError(f"background must be 3 values, got {background}")
        self.kwargs = dict(sigma=float(sigma), gamma=float(gamma), background=bg,
                           near=float(near), far=float(far), dist_eps=float(dist_eps),
                           max_pairs=int(max_pairs), checkpoint=bool(checkpoint))

    def __call__(self, mesh: Mesh, cams: Cameras) -> Dict[str, torch.Tensor]:
        """Render ``mesh`` from B cameras -> dict(image (B, H, W, 3), alpha (B, H, W))."""
        if mesh.has_texture:
            colors = dict(texture=mesh.texture, verts_uvs=mesh.verts_uvs, faces_uvs=mesh.faces_uvs)
        elif mesh.vert_colors is not None:
            colors = dict(vert_colors=mesh.vert_colors)
        else:
            colors = dict(vert_colors=torch.full_like(mesh.verts, 0.5))
        out = soft_rasterize(cams, mesh.verts, mesh.faces, **colors, **self.kwargs)
        return {"image": out["image"], "alpha": out["silhouette"]}
