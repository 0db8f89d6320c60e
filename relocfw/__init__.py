"""relocfw: plugin-based visual relocalization (6-DoF pose from one RGB image).

The package is six parts, imports running one way (app -> report -> model, data ->
core; structure -> data -> core), checked by tests/core/test_layout.py:

- `relocfw.core`: the plugin interfaces, values, the `Relocalizer` pipeline and its
  stages (scorer, search loop, sampling, the `PoseRefiner` interface),
  `QueryOptions`, geometry, cameras, imaging, descriptor standardisation. Plain
  Python + torch.
- `relocfw.model`: the pose head, loss, training, checkpoints, model files, ONNX.
- `relocfw.data`: dataset loaders and the synthetic scene.
- `relocfw.structure`: local features, matching, 3-D map points (depth, triangulation)
  and absolute pose solving, for structure-based refinement (`refine=features`).
- `relocfw.report`: evaluation, metrics, statistics over seeds, comparisons, figures,
  the crop-premise diagnosis.
- `relocfw.app`: the Hydra CLI, its tasks, plugin discovery, the torchrun entry.
"""

import importlib
import sys

from relocfw.core.errors import ConfigError, DataError, RelocfwError
from relocfw.core.interfaces import (
    Backbone,
    CropDistance,
    CropProposals,
    CropSearch,
    SearchQuery,
    SimilarityIndex,
)
from relocfw.core.pipeline import Relocalizer
from relocfw.core.query_options import QueryOptions
from relocfw.core.refinement import MapImage, PoseRefiner, Refined, RefineQuery
from relocfw.core.values import Crop, Localization, Pose, PoseOutput
from relocfw.core.version import VERSION
from relocfw.model.model_file import load_model, save_model

__all__ = [
    "Backbone",
    "ConfigError",
    "Crop",
    "CropDistance",
    "CropProposals",
    "CropSearch",
    "DataError",
    "Localization",
    "MapImage",
    "Pose",
    "PoseOutput",
    "PoseRefiner",
    "QueryOptions",
    "RefineQuery",
    "Refined",
    "Relocalizer",
    "RelocfwError",
    "SearchQuery",
    "SimilarityIndex",
    "load_model",
    "save_model",
]
__version__ = VERSION

# Plugins written for relocfw 0.1 import these modules from their first, flat paths
# (`relocfw.interfaces`, ...). The plugin API only grows within a major version
# (docs/plugins.md, "Versioning"), so those paths stay importable: each names the
# module itself, not a copy, so classes and isinstance checks are the same objects.
FLAT_PATHS = {
    "checkpoints": "relocfw.model.checkpoints",
    "contracts": "relocfw.core.contracts",
    "errors": "relocfw.core.errors",
    "geometry": "relocfw.core.geometry",
    "imaging": "relocfw.core.imaging",
    "interfaces": "relocfw.core.interfaces",
    "options": "relocfw.core.options",
    "pipeline": "relocfw.core.pipeline",
    "pose_head": "relocfw.model.pose_head",
    "sampling": "relocfw.core.sampling",
    "standardise": "relocfw.core.standardise",
    "values": "relocfw.core.values",
    "window_pooling": "relocfw.core.window_pooling",
}
for _flat, _moved in FLAT_PATHS.items():
    sys.modules.setdefault(f"relocfw.{_flat}", importlib.import_module(_moved))
    globals()[_flat] = sys.modules[f"relocfw.{_flat}"]  # relocfw.interfaces.Backbone too
del _flat, _moved
