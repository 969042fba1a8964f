"""l3d_app: learning-based 3D vision in one Hydra-configured PyTorch application.

Library code (everything except ``l3d_app.app`` and ``l3d_app.tasks``) takes plain
arguments and never imports Hydra.
"""

__version__ = "0.1.0"
