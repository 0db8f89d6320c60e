"""Map views as the structure builders read them: each checked as it is read
(`checked_views`, `checked_view`: every builder), and for the RGB-only builders read
once with its RootSIFT features on the stored descriptor grid (`features_of_views`)."""

from __future__ import annotations

from collections.abc import Sequence

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import DataError
from relocfw.core.progress import Progress
from relocfw.core.values import Pose
from relocfw.structure.features import LocalFeatures, checked_image_scale, extract_rootsift
from relocfw.structure.map_view import MapView
from relocfw.structure.structure_map import on_descriptor_grid


def checked_views(views: Sequence[MapView]) -> None:
    """A DataError unless `views` is a non-empty sequence (its entries are checked one
    at a time as they are read, `checked_view`, so a lazy sequence loads each once)."""
    if isinstance(views, MapView | str | bytes) or not isinstance(views, Sequence):
        raise DataError(f"views must be a sequence of MapView, got {type(views).__name__}")
    if len(views) == 0:
        raise DataError("views is empty: a structure map needs at least one map image")


def checked_view(number: int, view: object) -> MapView:
    """`view` itself when it is a MapView with a finite pose, else a DataError naming it."""
    if not isinstance(view, MapView):
        raise DataError(f"views[{number}] must be a MapView, got {type(view).__name__}")
    if not view.pose.is_finite:
        raise DataError(f"map view {view.name!r}: pose holds NaN or infinity")
    return view


def features_of_views(
    views: Sequence[MapView], max_features: int, progress: Progress, image_scale: float = 1.0
) -> tuple[list[LocalFeatures], list[Pose], list[PinholeCamera], list[str]]:
    """Each view read once, in order: its RootSIFT features (on the stored grid, SIFT
    at `image_scale`), pose, camera and name; one progress step per view."""
    image_scale = checked_image_scale(image_scale)
    features, poses, cameras, names = [], [], [], []
    for number in range(len(views)):
        view = checked_view(number, views[number])
        found = extract_rootsift(view.image, max_features, image_scale)
        features.append(on_descriptor_grid(found))
        poses.append(view.pose)
        cameras.append(view.camera)
        names.append(view.name)
        progress.advance(suffix="features")
    return features, poses, cameras, names
