"""Pinhole cameras: the library's single camera convention and converters to/from others.

Internal convention (OpenCV, column vectors), used everywhere inside ``l3d_app``:

* camera (view) frame: +X right, +Y down, +Z forward (into the scene);
* extrinsics ``X_cam = R @ X_world + t`` with ``R`` (B, 3, 3) world->camera, ``t`` (B, 3);
  the rows of ``R`` are the camera's right/down/forward axes in world coordinates and
  the camera centre is ``C = -R^T t``;
* intrinsics in pixels: ``u = fx * X/Z + cx``, ``v = fy * Y/Z + cy`` where ``u`` grows to
  the right (columns) and ``v`` downwards (rows);
* pixel centres at +0.5: pixel (row i, column j) has its centre at ``(u, v) = (j + .5, i + .5)``,
  so the image spans ``u`` in [0, W] and ``v`` in [0, H].

Converters at the input boundary (each with a round-trip test):

* PyTorch3D ``R, T`` (row vectors, ``X_view = X_world @ R + T``, view +X left, +Y up,
  +Z forward), focal/principal point in NDC units (``in_ndc=True``: pixel focal
  ``F * min(H, W) / 2``, principal point ``(W/2 - C0 * s/2, H/2 - C1 * s/2)`` with
  ``s = min(H, W)``) or in pixels (``in_ndc=False``);
* OpenGL / Blender camera-to-world 4x4 (camera +X right, +Y up, looking down -Z), as in
  NeRF ``transforms.json``;
* OpenCV ``R, t, K``.

``look_at(dist, elev, azim, at, up)`` places cameras exactly as PyTorch3D's
``look_at_view_transform`` does (degrees by default): eye =
``at + dist * (cos(elev) sin(azim), sin(elev), cos(elev) cos(azim))``, looking at ``at``
with ``up`` projected to the image's upward direction. If ``up`` is (nearly) parallel to
the viewing direction, where PyTorch3D returns a degenerate rotation, we replace ``up``
by the world axis most perpendicular to the viewing direction (ties go to the first of
X, Y, Z): the result is always a finite proper rotation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Sequence, Tuple, Union

import torch

from l3d_app.errors import UserError

Number = Union[float, int]
TensorLike = Union[torch.Tensor, Number, Sequence[Number]]

# Axis flips between the internal (OpenCV) frame and the others.
_FLIP_XY = (-1.0, -1.0, 1.0)  # PyTorch3D view (+X left, +Y up) <-> OpenCV (+X right, +Y down)
_FLIP_YZ = (1.0, -1.0, -1.0)  # OpenGL camera (+Y up, looks -Z) <-> OpenCV


def _diag(values, like: torch.Tensor) -> torch.Tensor:
    return torch.diag(torch.tensor(values, dtype=like.dtype, device=like.device))


def _batch(value: TensorLike, batch: int, dtype, device) -> torch.Tensor:
    """A (B,) float tensor from a scalar, a sequence or a tensor."""
    out = torch.as_tensor(value, dtype=dtype, device=device).reshape(-1)
    if out.numel() == 1:
        out = out.expand(batch)
    if out.numel() != batch:
        raise ValueError(f"expected 1 or {batch} values, got {out.numel()}")
    return out.contiguous()


@dataclass
class Cameras:
    """A batch of B pinhole cameras sharing one image size, in the internal convention.

    Attributes:
        R: (B, 3, 3) world->camera rotation.
        t: (B, 3) world->camera translation (world units).
        fx, fy: (B,) focal lengths in pixels.
        cx, cy: (B,) principal point in pixels (u right, v down, pixel centres at +0.5).
        width, height: image size in pixels.
    """

    R: torch.Tensor
    t: torch.Tensor
    fx: torch.Tensor
    fy: torch.Tensor
    cx: torch.Tensor
    cy: torch.Tensor
    width: int
    height: int

    def __post_init__(self):
        if self.R.dim() == 2:
            self.R = self.R[None]
        if self.t.dim() == 1:
            self.t = self.t[None]
        b, dt, dev = self.R.shape[0], self.R.dtype, self.R.device
        self.t = self.t.to(dt).expand(b, 3) if self.t.shape[0] == 1 else self.t.to(dt)
        for name in ("fx", "fy", "cx", "cy"):
            setattr(self, name, _batch(getattr(self, name), b, dt, dev))
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise UserError(f"image size must be positive, got {self.width}x{self.height}")
        self.width, self.height = int(self.width), int(self.height)

    # ----------------------------------------------------------------- basics
    @property
    def batch_size(self) -> int:
        return self.R.shape[0]

    @property
    def device(self) -> torch.device:
        return self.R.device

    def __len__(self) -> int:
        return self.batch_size

    def __getitem__(self, index) -> "Cameras":
        """Cameras for a subset of the batch (an int keeps the batch dimension)."""
        if isinstance(index, int):
            index = slice(index, index + 1) if index != -1 else slice(-1, None)
        return Cameras(self.R[index], self.t[index], self.fx[index], self.fy[index],
                       self.cx[index], self.cy[index], self.width, self.height)

    def to(self, device=None, dtype=None) -> "Cameras":
        moved = {f.name: getattr(self, f.name) for f in fields(self)}
        for k, v in moved.items():
            if torch.is_tensor(v):
                moved[k] = v.to(device=device, dtype=dtype)
        return Cameras(**moved)

    @property
    def image_size(self) -> Tuple[int, int]:
        """(H, W) in pixels."""
        return self.height, self.width

    def K(self) -> torch.Tensor:
        """(B, 3, 3) intrinsic matrices in pixels."""
        K = torch.zeros(self.batch_size, 3, 3, dtype=self.R.dtype, device=self.device)
        K[:, 0, 0], K[:, 1, 1] = self.fx, self.fy
        K[:, 0, 2], K[:, 1, 2] = self.cx, self.cy
        K[:, 2, 2] = 1.0
        return K

    def centers(self) -> torch.Tensor:
        """(B, 3) camera centres in world coordinates, ``C = -R^T t``."""
        return -(self.R.transpose(1, 2) @ self.t[..., None])[..., 0]

    def world_to_view(self, points: torch.Tensor) -> torch.Tensor:
        """World points (N, 3) or (B, N, 3) -> (B, N, 3) camera-frame points."""
        if points.dim() == 2:
            points = points[None].expand(self.batch_size, -1, -1)
        return points @ self.R.transpose(1, 2) + self.t[:, None, :]

    def view_to_pixels(self, view_points: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
        """Camera-frame points (B, N, 3) -> (B, N, 2) pixel coordinates (u, v).

        Points with ``|Z| < eps`` are divided by ``eps`` (sign kept) so the output stays
        finite; callers cull points behind the camera by depth.
        """
        z = view_points[..., 2]
        z = torch.where(z.abs() < eps, torch.where(z < 0, -eps, eps), z)
        u = self.fx[:, None] * view_points[..., 0] / z + self.cx[:, None]
        v = self.fy[:, None] * view_points[..., 1] / z + self.cy[:, None]
        return torch.stack([u, v], dim=-1)

    def project(self, points: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """World points (N, 3) or (B, N, 3) -> pixels (B, N, 2) and depth Z (B, N)."""
        view = self.world_to_view(points)
        return self.view_to_pixels(view), view[..., 2]

    # -------------------------------------------------------- constructors
    @staticmethod
    def from_fov(R: torch.Tensor, t: torch.Tensor, fov: TensorLike, width: int, height: int,
                 degrees: bool = True) -> "Cameras":
        """Cameras with a field of view ``fov`` across the SMALLER image side, centred.

        This matches PyTorch3D's FoV cameras on square images. fov in degrees by default.
        """
        fov_t = _batch(fov, R.shape[0] if R.dim() == 3 else 1, R.dtype, R.device)
        fov_rad = torch.deg2rad(fov_t) if degrees else fov_t
        if not torch.all((fov_rad > 0) & (fov_rad < math.pi)):
            raise UserError(f"field of view must be in (0, 180) degrees, got {fov}")
        focal = (min(width, height) / 2.0) / torch.tan(fov_rad / 2)
        return Cameras(R, t, focal, focal, width / 2.0, height / 2.0, width, height)

    def fov(self, degrees: bool = True) -> torch.Tensor:
        """(B,) field of view across the smaller image side (inverse of ``from_fov``)."""
        f = self.fx if self.width <= self.height else self.fy
        rad = 2 * torch.atan(min(self.width, self.height) / 2.0 / f)
        return torch.rad2deg(rad) if degrees else rad


# ------------------------------------------------------------- look-at
def look_at_rotation(eye: torch.Tensor, at: torch.Tensor, up: torch.Tensor,
                     eps: float = 1e-6) -> torch.Tensor:
    """(B, 3, 3) world->camera rotation of cameras at ``eye`` looking at ``at``.

    All inputs (B, 3). The image's upward direction is ``up`` projected orthogonally to
    the viewing direction; if ``up`` is parallel to it (cross product norm < eps) the
    world axis most perpendicular to the viewing direction is used instead.
    """
    z = torch.nn.functional.normalize(at - eye, dim=-1)
    up = up.expand_as(z)
    x = torch.cross(z, up, dim=-1)  # camera right = forward x up (down = -up)
    degenerate = x.norm(dim=-1, keepdim=True) < eps * up.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    if degenerate.any():
        # Most perpendicular world axis = smallest |z_i|; near-ties (rounding noise, e.g.
        # cos(pi/2) != 0 at elev = +-90) go to the first of X, Y, Z as documented.
        az = z.abs()
        tol = max(eps, 64 * torch.finfo(z.dtype).eps)
        near_min = az <= az.min(dim=-1, keepdim=True).values + tol
        first = torch.argmax(near_min.to(torch.uint8), dim=-1)
        axis = torch.nn.functional.one_hot(first, 3).to(z.dtype)
        x = torch.where(degenerate, torch.cross(z, axis, dim=-1), x)
    # Re-orthogonalise against z: when up is nearly parallel to z the cross product is
    # tiny and its rounding error would otherwise leave R visibly non-orthogonal.
    x = x - (x * z).sum(dim=-1, keepdim=True) * z
    x = torch.nn.functional.normalize(x, dim=-1)
    y = torch.cross(z, x, dim=-1)  # camera down
    return torch.stack([x, y, z], dim=1)


def look_at(dist: TensorLike = 1.0, elev: TensorLike = 0.0, azim: TensorLike = 0.0,
            at: TensorLike = (0.0, 0.0, 0.0), up: TensorLike = (0.0, 1.0, 0.0),
            degrees: bool = True, dtype=torch.float32, device=None
            ) -> Tuple[torch.Tensor, torch.Tensor]:
    """Extrinsics (R (B,3,3), t (B,3)) of cameras on a sphere around ``at``.

    Same placement as PyTorch3D's ``look_at_view_transform(dist, elev, azim)``; the batch
    size B is the broadcast of ``dist``, ``elev``, ``azim`` (and ``at``/``up`` rows).
    Returns the internal (OpenCV) convention; see the module docstring.
    """
    d, e, a = (torch.as_tensor(v, dtype=dtype, device=device).reshape(-1) for v in (dist, elev, azim))
    d, e, a = torch.broadcast_tensors(d, e, a)
    if degrees:
        e, a = torch.deg2rad(e), torch.deg2rad(a)
    at_t = torch.as_tensor(at, dtype=dtype, device=device).reshape(-1, 3)
    up_t = torch.as_tensor(up, dtype=dtype, device=device).reshape(-1, 3)
    offset = torch.stack([d * torch.cos(e) * torch.sin(a), d * torch.sin(e),
                          d * torch.cos(e) * torch.cos(a)], dim=-1)
    eye, at_b, up_b = torch.broadcast_tensors(at_t + offset, at_t, up_t)
    R = look_at_rotation(eye, at_b, up_b)
    t = -(R @ eye[..., None])[..., 0]
    return R, t


def look_at_cameras(dist: TensorLike, elev: TensorLike, azim: TensorLike, fov: TensorLike,
                    image_size: int, at: TensorLike = (0.0, 0.0, 0.0),
                    up: TensorLike = (0.0, 1.0, 0.0), device=None) -> Cameras:
    """Square-image cameras from ``look_at`` with a field of view in degrees."""
    R, t = look_at(dist, elev, azim, at=at, up=up, device=device)
    return Cameras.from_fov(R, t, fov, image_size, image_size)


# ------------------------------------------------------------ converters
def from_pytorch3d(R: torch.Tensor, T: torch.Tensor, focal: TensorLike,
                   principal_point: TensorLike = (0.0, 0.0), image_size: Tuple[int, int] = (256, 256),
                   in_ndc: bool = True) -> Cameras:
    """Cameras from PyTorch3D ``PerspectiveCameras`` parameters.

    Args:
        R: (B, 3, 3) or (3, 3), row-vector convention ``X_view = X_world @ R + T``.
        T: (B, 3) or (3,).
        focal: scalar, (B,), or (B, 2) (fx, fy); NDC units if ``in_ndc`` else pixels.
        principal_point: (2,) or (B, 2); NDC units if ``in_ndc`` else pixels.
        image_size: (H, W) in pixels.
    """
    R = R if R.dim() == 3 else R[None]
    T = T if T.dim() == 2 else T[None]
    b, dt, dev = R.shape[0], R.dtype, R.device
    H, W = int(image_size[0]), int(image_size[1])
    f = torch.as_tensor(focal, dtype=dt, device=dev)
    f = f.reshape(-1, 2) if f.numel() == 2 * b and f.shape[-1:] == (2,) else f.reshape(-1, 1).expand(-1, 2)
    pp = torch.as_tensor(principal_point, dtype=dt, device=dev).reshape(-1, 2)
    if in_ndc:
        s = min(H, W) / 2.0
        fx, fy = f[:, 0] * s, f[:, 1] * s
        px, py = W / 2.0 - pp[:, 0] * s, H / 2.0 - pp[:, 1] * s
    else:
        fx, fy, px, py = f[:, 0], f[:, 1], pp[:, 0], pp[:, 1]
    flip = _diag(_FLIP_XY, R)
    return Cameras(flip @ R.transpose(1, 2), T.to(dt) @ flip, fx, fy, px, py, W, H)


def to_pytorch3d(cams: Cameras, in_ndc: bool = True):
    """Inverse of :func:`from_pytorch3d`: returns (R, T, focal (B, 2), principal_point (B, 2))."""
    flip = _diag(_FLIP_XY, cams.R)
    R = (flip @ cams.R).transpose(1, 2)
    T = cams.t @ flip
    focal = torch.stack([cams.fx, cams.fy], -1)
    pp = torch.stack([cams.cx, cams.cy], -1)
    if in_ndc:
        s = min(cams.width, cams.height) / 2.0
        focal = focal / s
        pp = torch.stack([(cams.width / 2.0 - cams.cx) / s, (cams.height / 2.0 - cams.cy) / s], -1)
    return R, T, focal, pp


def from_opengl_c2w(c2w: torch.Tensor, fx: TensorLike, fy: TensorLike, cx: TensorLike,
                    cy: TensorLike, width: int, height: int) -> Cameras:
    """Cameras from OpenGL/Blender camera-to-world matrices (B, 4, 4) or (B, 3, 4).

    OpenGL camera frame: +X right, +Y up, looking down -Z (NeRF ``transforms.json``).
    """
    c2w = c2w if c2w.dim() == 3 else c2w[None]
    rot_gl, centre = c2w[:, :3, :3], c2w[:, :3, 3]
    flip = _diag(_FLIP_YZ, c2w)
    R = flip @ rot_gl.transpose(1, 2)
    t = -(R @ centre[..., None])[..., 0]
    return Cameras(R, t, fx, fy, cx, cy, width, height)


def to_opengl_c2w(cams: Cameras) -> torch.Tensor:
    """(B, 4, 4) OpenGL camera-to-world matrices; inverse of :func:`from_opengl_c2w`."""
    flip = _diag(_FLIP_YZ, cams.R)
    c2w = torch.zeros(cams.batch_size, 4, 4, dtype=cams.R.dtype, device=cams.device)
    c2w[:, :3, :3] = cams.R.transpose(1, 2) @ flip
    c2w[:, :3, 3] = cams.centers()
    c2w[:, 3, 3] = 1.0
    return c2w


def from_opencv(R: torch.Tensor, t: torch.Tensor, K: torch.Tensor, width: int, height: int) -> Cameras:
    """Cameras from OpenCV ``R`` (B,3,3), ``t`` (B,3) and ``K`` (B,3,3) or (3,3)."""
    K = K if K.dim() == 3 else K[None]
    return Cameras(R, t, K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], width, height)


def to_opencv(cams: Cameras) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(R, t, K): inverse of :func:`from_opencv`."""
    return cams.R, cams.t, cams.K()


def stack_cameras(cams: Sequence[Cameras]) -> Cameras:
    """Concatenate camera batches that share an image size."""
    sizes = {(c.width, c.height) for c in cams}
    if len(sizes) != 1:
        raise ValueError(f"cannot stack cameras with different image sizes {sizes}")
    cat = lambda name: torch.cat([getattr(c, name) for c in cams])  # noqa: E731
    return Cameras(cat("R"), cat("t"), cat("fx"), cat("fy"), cat("cx"), cat("cy"),
                   cams[0].width, cams[0].height)

