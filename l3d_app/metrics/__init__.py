"""Metrics: PSNR / SSIM, chamfer, F-score, IoU, accuracy, surface scores. Pure functions of
tensors and geometry; metrics never render and never load data. (``fscore``, ``iou``, ``accuracy`` and
``surface_scores`` share their module's name: import them from it, ``from l3d_app.metrics.iou import iou``.)"""

from l3d_app.exports import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {
    "psnr": "image",
    "ssim": "image",
    "chamfer_distance": "chamfer",
    "nearest_neighbors": "chamfer",
    "check_image": "prompt_match",
})
