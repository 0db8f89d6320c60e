"""The RGB-only builders behind one name: `refine.triangulation.method` picks
multi-view tracks (the default) or the earlier two-view medians."""

from __future__ import annotations

import inspect
from collections.abc import Sequence
from typing import Any

from relocfw.core.errors import ConfigError
from relocfw.structure.map_view import MapView
from relocfw.structure.structure_map import StructureMap
from relocfw.structure.track_structure import build_by_track_triangulation
from relocfw.structure.two_view_structure import build_by_two_view_triangulation

TRIANGULATION_METHODS = ("tracks", "two_view")


def build_by_triangulation(
    views: Sequence[MapView],
    max_features: int = 1024,
    method: str = "tracks",
    quiet: bool = False,
    image_scale: float = 1.0,
    **settings: Any,
) -> StructureMap:
    """The structure of RGB map images of known pose: multi-view tracks
    (`build_by_track_triangulation`, method "tracks") or the earlier two-view
    medians (`build_by_two_view_triangulation`, method "two_view"); `settings` go to
    the chosen builder.

    Raises:
        ConfigError: when `method` is not one of TRIANGULATION_METHODS, or a setting
            is not the chosen builder's (naming it).
    """
    if method == "tracks":
        return build_by_track_triangulation(
            views, max_features, quiet=quiet, image_scale=image_scale, **settings
        )
    if method == "two_view":
        allowed = set(inspect.signature(build_by_two_view_triangulation).parameters)
        for key in settings:
            if key not in allowed or key in ("views", "max_features", "quiet", "image_scale"):
                raise ConfigError(f"triangulation.{key} is not a setting of method two_view")
        return build_by_two_view_triangulation(
            views, max_features, quiet=quiet, image_scale=image_scale, **settings
        )
    choices = ", ".join(TRIANGULATION_METHODS)
    raise ConfigError(f"triangulation.method must be one of {choices}, got {method!r}")
