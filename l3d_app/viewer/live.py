"""A viser page that shows a model as it trains: rendered from each browser's own camera.

Two threads share the work, and neither waits for the other:

* the training thread only calls :meth:`LiveViewer.observe` (a watcher of the run's logger:
  each logged scalar). It records the step, the loss and the validation PSNR, and, only while
  a page is open and at most every ``period`` seconds, takes a snapshot of the model
  (``snapshot()``, a detached copy) at that step. With no page open it does nothing else, so
  training is not slowed.
* the viewer's own thread renders the latest snapshot (``render(snapshot, camera)``, no
  gradients) for every open page whose camera moved or whose snapshot is older than the
  latest, and sends the picture as the page's background image. Training goes on meanwhile
  (it shares the CPU with those renders).

The page also shows the training cameras as frustums, and the step, loss and validation PSNR.
"""

from __future__ import annotations

import sys
import threading
import time
from typing import Any, Callable, Dict, Optional

import numpy as np
import torch

from l3d_app.errors import UserError
from l3d_app.geometry.cameras import Cameras
from l3d_app.viewer.camera_frames import cameras_to_viser, viser_to_cameras

Render = Callable[[Any, Cameras], torch.Tensor]     # (snapshot, one camera) -> (H, W, 3) in [0, 1]


def import_viser():
    """viser, or a one-line :class:`UserError` naming the extra that installs it."""
    try:
        import viser
    except ImportError:
        raise UserError("the viewer needs viser: pip install -e '.[viewer]' (the viewer extra)") from None
    return viser


class LiveViewer:
    """Serve a page at ``http://host:port`` that draws ``render(snapshot, camera)`` for each browser.

    Args:
        snapshot: () -> a frozen copy of the model (called on the training thread).
        render: :data:`Render`, called on the viewer's thread under ``torch.no_grad``.
        host, port: where to serve (port 0: a free port).
        width: width (px) of the pictures rendered for a page (height from the page's aspect).
        period: fewest seconds between two snapshots while a page is open.
        title: the page's heading.
    """

    def __init__(self, snapshot: Callable[[], Any], render: Render, host: str = "127.0.0.1", port: int = 8080,
                 width: int = 256, period: float = 1.0, title: str = "l3d_app"):
        viser = import_viser()
        if port == 0:
            import socket

            with socket.socket() as s:
                s.bind((host, 0))
                port = s.getsockname()[1]
        try:
            self.server = viser.ViserServer(host=host, port=int(port), verbose=False)
        except OSError as err:
            raise UserError(f"the viewer cannot serve on {host}:{port} ({err.strerror or err}): "
                            "set +viewer_port=N (0: any free port)") from None
        self.snapshot_fn, self.render_fn = snapshot, render
        self.width, self.period, self.title = int(width), float(period), title
        self.url = f"http://{host}:{self.server.get_port()}"
        self.stats: Dict[str, float] = {}
        self.model, self.model_step, self.version = None, -1, 0
        self.want_snapshot = False
        self.last_snapshot = 0.0
        self.snapshots = 0                       # snapshots taken (what watching cost the training thread)
        self.sent: Dict[int, Any] = {}           # client id -> (camera key, version) last drawn
        self.last_image: Dict[int, np.ndarray] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._shown = 0.0
        self.status = self.server.gui.add_markdown(self._status_text())
        self.server.on_client_connect(self._on_connect)
        self._thread = threading.Thread(target=self._serve, name="l3d-viewer", daemon=True)
        self._thread.start()

    # -------------------------------------------------------------- the training thread
    def observe(self, tag: str, value: float, step: int) -> None:
        """A logged scalar (the run logger's watcher): record it; snapshot the model when a page wants one."""
        if tag.endswith("/loss") and tag.startswith("train"):
            self.stats["loss"] = float(value)
        elif tag == "val/psnr":
            self.stats["val_psnr"] = float(value)
        elif tag.startswith("time/"):
            return
        self.stats["step"] = int(step)
        now = time.perf_counter()
        if now - self._shown > 0.5:
            self._shown = now
            self.status.content = self._status_text()
        if self.want_snapshot or (self.sent and now - self.last_snapshot >= self.period and self.server.get_clients()):
            self.publish(int(step))

    def publish(self, step: int) -> None:
        """Take a snapshot of the model now (training thread) as the one pages draw."""
        model = self.snapshot_fn()
        with self._lock:
            self.model, self.model_step = model, int(step)
            self.version += 1
        self.want_snapshot = False
        self.last_snapshot = time.perf_counter()
        self.snapshots += 1

    # -------------------------------------------------------------- the page
    def _status_text(self) -> str:
        s = self.stats
        rows = [f"**{self.title}**", f"step: **{s['step']}**" if "step" in s else "step: -"]
        if "loss" in s:
            rows.append(f"loss: {s['loss']:.5f}")
        if "val_psnr" in s:
            rows.append(f"val PSNR: {s['val_psnr']:.2f} dB")
        rows.append(f"model shown: step {self.model_step}" if self.model_step >= 0 else "model shown: waiting")
        return "  \n".join(rows)

    def add_cameras(self, cameras: Cameras, images: Optional[torch.Tensor] = None, scale: float = 0.1,
                    up: Optional[torch.Tensor] = None, look_at: Optional[torch.Tensor] = None) -> None:
        """Draw ``cameras`` as frustums (``images`` (N, H, W, 3): small pictures in them); pages start a
        little behind the first camera, looking at ``look_at``, with ``up`` as the orbit's up direction."""
        wxyz, pos, fov, aspect = cameras_to_viser(cameras)
        for i in range(len(pos)):
            thumb = None
            if images is not None:
                img = images[i].detach().float().cpu()
                step = max(1, img.shape[1] // 64)
                thumb = (img[::step, ::step].clamp(0, 1).numpy() * 255).astype(np.uint8)
            self.server.scene.add_camera_frustum(f"/cameras/{i:04d}", fov=float(fov[i]), aspect=aspect, scale=scale,
                                                 wxyz=wxyz[i], position=pos[i], image=thumb, format="jpeg",
                                                 color=(40, 90, 200))
        if len(pos):       # behind the first camera (not inside its frustum), looking at ``look_at``
            target = pos[0] + (cameras.R[0, 2].double().cpu().numpy() if look_at is None else
                               np.asarray(look_at, dtype=np.float64) - pos[0])
            self.server.initial_camera.position = tuple(float(v) for v in target + 1.3 * (pos[0] - target))
            self.server.initial_camera.look_at = tuple(float(v) for v in target)
            self.server.initial_camera.fov = float(fov[0])
        if up is not None:
            self.server.initial_camera.up = tuple(float(v) for v in up)

    def _on_connect(self, client) -> None:
        self.want_snapshot = self.model is None or self.want_snapshot
        client.camera.on_update(lambda _cam: None)      # camera moves arrive; the serving loop reads them

    # -------------------------------------------------------------- the viewer's thread
    def _serve(self) -> None:
        torch.set_grad_enabled(False)
        while not self._stop.is_set():
            drew = False
            try:
                clients = self.server.get_clients()
            except Exception:        # the server is shutting down
                break
            for cid in [c for c in self.sent if c not in clients]:
                self.sent.pop(cid, None)
            for cid, client in clients.items():
                if self.model is None:
                    self.want_snapshot = True
                    self.sent.setdefault(cid, None)
                    continue
                cam = client.camera
                key = (tuple(np.round(cam.wxyz, 6)), tuple(np.round(cam.position, 6)), round(float(cam.fov), 6),
                       round(float(cam.aspect), 4))
                with self._lock:
                    model, version = self.model, self.version
                if self.sent.get(cid) == (key, version):
                    continue
                cameras = viser_to_cameras(cam.wxyz, cam.position, cam.fov, cam.aspect, self.width)
                try:
                    img = self.render_fn(model, cameras)
                except Exception as err:   # a render failure must not stop training: say it once per client
                    print(f"l3d_app: warning: the viewer could not render: {type(err).__name__}: {err}", file=sys.stderr)
                    self.sent[cid] = (key, version)
                    continue
                pic = (img.detach().float().clamp(0, 1).cpu().numpy() * 255).astype(np.uint8)
                client.scene.set_background_image(pic, format="jpeg", jpeg_quality=90)
                self.last_image[cid] = pic
                self.sent[cid] = (key, version)
                drew = True
            if not drew:
                self._stop.wait(0.05)

    def close(self) -> None:
        """Stop serving (the page says it lost the connection)."""
        self._stop.set()
        self._thread.join(timeout=5)
        self.server.stop()
