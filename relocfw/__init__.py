"""relocfw: plugin-based visual relocalization (6-DoF pose from one RGB image)."""

from relocfw.errors import ConfigError, DataError, RelocfwError
from relocfw.interfaces import Backbone, CropDistance, CropSearch, SimilarityIndex
from relocfw.pipeline import Relocalizer
from relocfw.values import Crop, Localization, Pose, PoseOutput

__all__ = [
    "Backbone",
    "ConfigError",
    "Crop",
    "CropDistance",
    "CropSearch",
    "DataError",
    "Localization",
    "Pose",
    "PoseOutput",
    "Relocalizer",
    "RelocfwError",
    "SimilarityIndex",
]
__version__ = "0.1.0"
