"""Ray-sample estimators (registry ``SAMPLERS``, config group ``sampler=``).

Each estimator answers WHERE to sample along rays with
``sampling(origins, dirs, ...) -> (t_starts, t_ends, ray_indices)`` (packed, see
:mod:`l3d_app.render.volume.rendering`) and keeps any state it learns from the field with
``update(step, field, generator)``, called before the training step ``step`` renders (and
before an evaluation at ``step``; a second call for the same step does nothing). A new
estimator is one file here with ``@SAMPLERS.register("name")``, a line below and a yaml
in ``conf/sampler/``.
"""

from l3d_app.render.volume.estimators.base import Estimator
from l3d_app.render.volume.estimators.hierarchical import HierarchicalEstimator
from l3d_app.render.volume.estimators.importance import ImportanceEstimator
from l3d_app.render.volume.estimators.occupancy import OccupancyEstimator
from l3d_app.render.volume.estimators.sdf_proposal import SDFCacheProposal
from l3d_app.render.volume.estimators.stratified import StratifiedEstimator

__all__ = ["Estimator", "StratifiedEstimator", "OccupancyEstimator", "ImportanceEstimator", "HierarchicalEstimator",
           "SDFCacheProposal"]
