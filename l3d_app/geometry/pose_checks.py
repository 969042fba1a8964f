"""Checks on camera poses read from files: finite and rigid, or one clear line naming the frame.

Every multi-view loader passes its world->camera rotations (or camera->world rotation
blocks; the test is the same on the transpose) through :func:`check_rigid_poses` before
building :class:`~l3d_app.geometry.cameras.Cameras`, so a NaN or a scaled / sheared
matrix in a ``transform_matrix`` stops the run at load time with the file and the frame
named instead of training silently on garbage.
"""

from __future__ import annotations

from typing import Optional, Sequence

import torch

from l3d_app.errors import UserError


def check_rigid_poses(R: torch.Tensor, t: Optional[torch.Tensor], source: str,
                      frame_names: Optional[Sequence[str]] = None, tol: float = 1e-3) -> None:
    """Raise :class:`UserError` unless every pose is finite and ``R`` a proper rotation.

    Args:
        R: (B, 3, 3) rotation blocks (either direction: orthonormality is transpose-invariant).
        t: (B, 3) translations or None.
        source: the file (or folder) the poses came from, for the message.
        frame_names: B names (file names or ``frame i``) for the message.
        tol: max |R^T R - I| entry and |det R - 1| allowed (the files store ~6 digits).
    """
    R = torch.as_tensor(R, dtype=torch.float64).reshape(-1, 3, 3)
    name = (lambda i: str(frame_names[i])) if frame_names is not None else (lambda i: f"frame {i}")
    finite = torch.isfinite(R).flatten(1).all(1)
    if t is not None:
        finite &= torch.isfinite(torch.as_tensor(t, dtype=torch.float64).reshape(-1, 3)).all(1)
    if not bool(finite.all()):
        i = int((~finite).nonzero()[0])
        raise UserError(f"{source}: {name(i)}: camera pose has a non-finite value (NaN or inf)")
    eye = torch.eye(3, dtype=torch.float64)
    ortho = (R.transpose(1, 2) @ R - eye).abs().flatten(1).amax(1)
    det = torch.linalg.det(R)
    bad = (ortho > tol) | ((det - 1.0).abs() > tol)
    if bool(bad.any()):
        i = int(bad.nonzero()[0])
        raise UserError(f"{source}: {name(i)}: camera rotation is not rigid "
                        f"(|R^T R - I| = {float(ortho[i]):.3g}, det = {float(det[i]):.4g})")


def check_finite(values: torch.Tensor, source: str, what: str) -> None:
    """Raise :class:`UserError` naming the first row of ``values`` (N, ...) that holds NaN/inf."""
    v = torch.as_tensor(values)
    ok = torch.isfinite(v.reshape(v.shape[0], -1)).all(1) if v.numel() else torch.ones(0, dtype=torch.bool)
    if not bool(ok.all()):
        i = int((~ok).nonzero()[0])
        raise UserError(f"{source}: {what} {i} has a non-finite value (NaN or inf)")
