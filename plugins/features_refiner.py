"""refine=features / features_rgb: local features of the query against keyframes of the
map, 2-D/3-D correspondences, absolute pose by LO-RANSAC (relocfw.structure).

The structure-based family (hloc's): per map image RootSIFT keypoints with a 3-D point
each, lifted with the map image's depth (`structure=depth`), triangulated between
map images with their known poses (`structure=triangulated`, for users without depth)
or taken from a COLMAP model's own points3D (`structure=colmap`: each keypoint gets
the point of the model's observation it sits on, relocfw.structure.colmap_structure).
`structure=depth` on map images that have no depth map but carry a COLMAP model's
observations (dataset=colmap, dataset.points=true) uses those: a model's points are
measured 3-D, as depth is, so `refine=features` on dataset=colmap solves against them.
Per query: retrieve `count` keyframes, by the chosen crop's descriptor (with crop=ga,
the paper's idea applied to retrieval), by the network's pose, or by the last confident
pose of the query's stream (`keyframes=track`, below); match, solve. With fewer than
`min_inliers` inliers it answers the network's pose, flagged as fallen back; so it does
when the network's pose is not finite and keyframes are chosen by it (no keyframe is
near a NaN pose: the refiner cannot do better than the network, which is the
contract's fallback, and one broken query does not stop an evaluation).

Tracking (`keyframes=track`). Keyframes near the network's regressed pose did best in
the project's Red Kitchen measurements (docs/results/structure.md: keyframes=pose ahead
of retrieval), and consecutive frames of a recording move a few centimetres, so the
pose solved for the previous frame is a far closer prior still. The queries of one
stream (relocfw.structure.tracking_prior: the name's part before its last "/")
arrive in order (evaluation, task=localize), so each query whose stream has a
confident pose is matched against the keyframes near it. When that fails (the track
is lost: a fast turn, a blurred frame) the same query is retried by descriptor
retrieval, so a lost track costs one more solve, not the answer (a tracked solve that
succeeds with a wrong pose is kept, and becomes the next frame's prior); its
seconds then add both attempts per part, with the retry's in "tracking_retry". A
stream without a confident pose (its first frame, or after a fallback) starts from
retrieval; `reset` forgets every stream.

Matching again (`rematch=near` or `union`). Keyframes found by descriptor are the map
images that look like the query, not always the ones that see what it sees from where
it stands. After a first solve that succeeds, the query is matched again (its local
features reused) against the `count` keyframes nearest the solved pose, looking its
way (`near`), or against those together with the first solve's keyframes (`union`:
both what looks alike and what stands near), and the second solve answers where it
succeeds too; otherwise the first stands. With `rematch_answer=more_inliers` the
second answers only where it has at least as many inliers (distinct query keypoints) as
the first: a second keyframe set that sees less of the query is then not trusted
over the first. Its seconds add both solves per part, the second's also in "rematch".

On a map that is not metric (refine.metric=false, set from dataset.metric: an
unaligned COLMAP model), the default triangulation (refine.triangulation.method=
tracks) is unchanged: all its settings are angles, pixels and counts. Only
method=two_view has a length in metres, its 5 cm smallest baseline, which is then
measured against the map instead: half the median distance between a map image and
its nearest other map image (the bound's job is to skip partners standing almost
where the image stands, and in a map of unknown scale "almost" can only be told from
how far apart its images usually are). Depth maps are refused there (they are in
metres and cannot be lifted into poses that are not); a COLMAP model's points are in
its own units, as its poses, so they serve at any scale.

Model files (format 5) keep the fitted refiner whole (`state` / `load_state`: the map's
structure as flat arrays, relocfw.structure.map_state, the keyframe descriptors and
the query options), so a loaded model needs no map image, depth file or cache.

Large maps (`map_store=compact`, `keyframe_search=faiss`). A StructureMap holds every
map image's float32 descriptors in memory; with map_store=compact the map, built or
read from the structure cache as always, is written once as a compact map folder
beside its cache entry (relocfw.structure.compact_cache: uint8 grid descriptors, the
exact ones, and float16 camera-frame points, only keypoints with a 3-D point),
dropped from memory, and each query reads its keyframes from that folder, memory-
mapped (CompactMap.keyframe_map). Matching only keypoints with a point is then the
only choice (match_points_only=true), and the folder needs cache_dir. A model file
stores the compact arrays themselves (relocfw.structure.compact_state), so it stays
one self-contained file. keyframe_search=faiss retrieves keyframes by descriptor with
faiss's exact flat search (relocfw.structure.faiss_keyframes) instead of numpy's.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.options import positive_number
from relocfw.core.refinement import MapImage, PoseRefiner, Refined, RefineQuery
from relocfw.core.sensor_poses import (
    colour_pose,
    map_pose_to_colour,
    pose_to_colour_state,
    reference_pose,
    stored_pose_to_colour,
)
from relocfw.core.standardise import ZScore, check_features
from relocfw.core.values import Pose
from relocfw.structure import (
    MapView,
    MapViewpoints,
    StructureMap,
    build_by_triangulation,
    build_from_colmap_points,
    build_from_depth,
    cached_structure_map,
    keyframes_by_pose,
    localize_against,
    structure_key,
)
from relocfw.structure.absolute_pose import POSELIB_MIN_ITERATIONS
from relocfw.structure.colmap_structure import checked_radius
from relocfw.structure.compact_cache import cached_compact_map
from relocfw.structure.compact_map import CompactMap
from relocfw.structure.compact_state import compact_of_state, compact_state, holds_compact_map
from relocfw.structure.faiss_keyframes import FaissKeyframeSearch, imported_faiss
from relocfw.structure.features import LocalFeatures, checked_image_scale
from relocfw.structure.map_state import map_of_state, map_state
from relocfw.structure.match_index import KnownMatches, MatchIndex
from relocfw.structure.refiner_inputs import (
    builder_parameters,
    checked_triangulation,
    has_depth_file,
    has_observations,
    keyframes_by_descriptor,
    map_camera,
    query_camera,
    structure_settings,
)
from relocfw.structure.refiner_state import (
    STATE_INTEGERS,
    STATE_LABEL,
    STATE_NUMBERS,
    checked_choice,
    checked_keyframes_choice,
    checked_min_iterations,
    checked_size,
    options_state,
    stored_keyframe_descriptors,
    stored_options,
)
from relocfw.structure.tracking_prior import LastConfidentPoses

STRUCTURES = ("depth", "triangulated", "colmap")
NO_DEPTH_HINT = (
    "use refine=features_rgb, which triangulates the map's points from its images and "
    "poses, or, for a COLMAP model, dataset=colmap with dataset.points=true and the "
    "model's points3D file (refine=features_colmap)"
)


class FeaturesRefiner(PoseRefiner):
    """Local features + PnP against the map's structure.

    Args:
        structure: "depth" (3-D points from the map images' depth maps; a COLMAP
            model's points where the map images have no depth but carry those),
            "triangulated" (between map images with their known poses; RGB only)
            or "colmap" (a COLMAP model's points3D, Frame.observations).
        keyframes: "descriptor" (the map images nearest to the chosen crop's
            descriptor), "pose" (nearest to the network's pose, looking the same way)
            or "track" (nearest to the last confident pose of the query's stream,
            retrieval by descriptor without one or when it fails; see the module).
        count: keyframes per query.
        max_features: most RootSIFT keypoints per image (map and query).
        ratio: Lowe's ratio test of the mutual nearest neighbours.
        max_error_px: reprojection error under which a correspondence is an inlier.
        min_inliers: fewest inliers for a pose; below, the network's pose stands.
        cache_dir: where the map's structure is cached by content (None: not cached).
        quiet: no progress bars.
        metric: whether the map's poses are in metres (dataset.metric); False scales
            the two-view triangulation's metric bound to the map and refuses depth
            maps (the track builder's settings are scale-free).
        radius_px: structure=colmap: the farthest a COLMAP observation may be from
            the keypoint that takes its 3-D point.
        triangulation: how structure=triangulated builds its points (method tracks or
            two_view and the track settings, relocfw.structure.tracks.TrackSettings);
            None: the defaults. Checked here, each key named.
        image_scale: the share of each image side SIFT runs at, map and query, in
            (0, 1] (0.5: a quarter of the pixels, about 4x faster extraction).
        match_points_only: match queries only against map keypoints that have a 3-D
            point (relocfw.structure.match_index); false: against every keypoint.
        ransac_min_iterations: the solve's fewest RANSAC rounds (PoseLib's 1000 by
            default; more stop by its confidence rule).
        map_store: "memory" (the StructureMap) or "compact" (written once beside the
            structure cache and read memory-mapped, keyframe by keyframe; needs
            cache_dir and match_points_only; see the module).
        keyframe_search: "numpy" or "faiss" (exact flat search; relocfw[faiss]): how
            keyframes are found by descriptor.
        rematch: "none"; "near" (after a solve that succeeds, match the query again
            against the `count` keyframes nearest the solved pose, looking its way, and
            answer that second solve where it succeeds too) or "union" (the same with
            the first solve's keyframes added); see the module.
        rematch_answer: which solve answers a query matched again: "second" (the
            second where it succeeds) or "more_inliers" (the second where it succeeds
            with at least as many inliers as the first, else the first).
    """

    def __init__(
        self,
        structure: str = "depth",
        keyframes: str = "descriptor",
        count: int = 10,
        max_features: int = 1024,
        ratio: float = 0.8,
        max_error_px: float = 8.0,
        min_inliers: int = 12,
        cache_dir: str | Path | None = None,
        quiet: bool = False,
        metric: bool = True,
        radius_px: float = 2.5,
        triangulation: Mapping[str, Any] | None = None,
        image_scale: float = 1.0,
        match_points_only: bool = True,
        ransac_min_iterations: int = POSELIB_MIN_ITERATIONS,
        map_store: str = "memory",
        keyframe_search: str = "numpy",
        rematch: str = "none",
        rematch_answer: str = "second",
    ) -> None:
        # Every option is checked here, before training and the map's structure, and
        # named as the command line spells it (refine.ratio, ...).
        if structure not in STRUCTURES:
            choices = ", ".join(STRUCTURES)
            raise ConfigError(f"refine.structure must be one of {choices}, got {structure!r}")
        self.structure_source = structure
        self.keyframes = checked_keyframes_choice(keyframes)
        self.count = checked_size("count", count, STATE_INTEGERS["count"])
        self.max_features = checked_size(
            "max_features", max_features, STATE_INTEGERS["max_features"]
        )
        self.ratio = positive_number("refine.ratio", ratio, most=1.0)
        self.max_error_px = checked_size("max_error_px", max_error_px)
        self.min_inliers = checked_size("min_inliers", min_inliers, STATE_INTEGERS["min_inliers"])
        self.cache_dir = None if cache_dir is None else Path(cache_dir).expanduser()
        self.quiet = bool(quiet)
        if not isinstance(metric, bool):
            raise ConfigError(f"refine.metric must be true or false, got {metric!r}")
        self.metric = metric
        self.radius_px = checked_radius(radius_px)
        # Checked even for structure=depth: a typo there should not wait for the
        # day the same config is run with features_rgb.
        self.triangulation = checked_triangulation(triangulation)
        try:
            self.image_scale = checked_image_scale(image_scale)
        except ConfigError as error:
            raise ConfigError(f"refine.{error}") from None
        if not isinstance(match_points_only, bool):
            raise ConfigError(
                f"refine.match_points_only must be true or false, got {match_points_only!r}"
            )
        self.match_points_only = match_points_only
        self.ransac_min_iterations = checked_min_iterations(ransac_min_iterations)
        self.map_store = checked_choice("map_store", map_store)
        self.check_map_store()
        self.keyframe_search = checked_choice("keyframe_search", keyframe_search)
        if self.keyframe_search == "faiss":
            imported_faiss()  # a missing faiss is said now, not after training
        self.rematch = checked_choice("rematch", rematch)
        self.rematch_answer = checked_choice("rematch_answer", rematch_answer)
        self.tracked = LastConfidentPoses()  # keyframes=track's prior, per stream
        # The fitted map: a StructureMap (map_store=memory) or a CompactMap (compact).
        self.structure: StructureMap | None = None
        self.compact: CompactMap | None = None
        self.skipped: tuple = ()
        # Where the map images stand and look (keyframes by pose), on first use.
        self.viewpoints: MapViewpoints | None = None
        self.keyframe_index: FaissKeyframeSearch | None = None

    def check_map_store(self) -> None:
        """A ConfigError where map_store=compact cannot be: without match_points_only
        (the compact map has no keypoint without a point) or without cache_dir (its
        folder goes beside the structure cache)."""
        if self.map_store != "compact":
            return
        if not self.match_points_only:
            raise ConfigError(
                "refine.map_store=compact keeps only the map keypoints that have a 3-D "
                "point, so it needs refine.match_points_only=true (got false)"
            )
        if self.cache_dir is None:
            raise ConfigError(
                "refine.map_store=compact writes the map as a folder beside the structure "
                "cache, so it needs a cache_dir (refine.cache_dir is null)"
            )

    def source_for(self, frames: Sequence[object]) -> str:
        """The builder the map gets: refine.structure, except that structure=depth on
        map images without a depth file that carry a COLMAP model's observations
        takes the model's points ("colmap"; see the module)."""
        if (
            self.structure_source == "depth"
            and not any(has_depth_file(f) for f in frames)
            and any(has_observations(f) for f in frames)
        ):
            return "colmap"
        return self.structure_source

    def check_source(self, frames: Sequence[object], depth_files: bool = True) -> str:
        """source_for(frames), or a ConfigError where the map images cannot give it
        (`depth_files`: also when none names an existing depth file; fit leaves that
        to the build, whose message names the first file that failed)."""
        source = self.source_for(frames)
        if source == "depth" and not self.metric:
            raise ConfigError(
                "refine=features lifts depth maps (metres) into the map's poses, which "
                f"are not metric here (dataset.metric=false); {NO_DEPTH_HINT}"
            )
        if source == "depth" and depth_files and not any(has_depth_file(f) for f in frames):
            raise ConfigError(
                f"refine=features needs depth maps, and none of the {len(frames)} map "
                f"images has one; {NO_DEPTH_HINT}"
            )
        if source == "colmap" and not any(has_observations(f) for f in frames):
            raise ConfigError(
                "refine.structure=colmap needs a COLMAP model's 3-D points, and none of "
                f"the {len(frames)} map images carries any (dataset=colmap with "
                "dataset.points=true and a model holding points3D); use "
                "refine=features_rgb to triangulate them from the images and poses"
            )
        return source

    def settings(self, views: Sequence[MapImage], parameters: dict | None = None) -> dict:
        """The map structure's cache key besides names, poses and cameras
        (refiner_inputs.structure_settings). `parameters`: build_parameters(views),
        where the caller has them already (a non-metric map's spacing is O(M^2))."""
        if parameters is None:
            parameters = self.build_parameters(views)
        source = self.source_for(views)
        settings = structure_settings(source, self.max_features, views, parameters)
        if self.image_scale != 1.0:
            # Only here, so maps at full size keep the keys (and caches) they had.
            settings["image_scale"] = self.image_scale
        return settings

    def build_parameters(self, views: Sequence[MapImage]) -> dict:
        """The builder's keyword arguments (refiner_inputs.builder_parameters; for
        structure=colmap, radius_px)."""
        source = self.source_for(views)
        if source == "colmap":
            return {"radius_px": self.radius_px}
        return builder_parameters(source, self.metric, views, self.triangulation)

    def check_map(self, frames: Sequence[object]) -> None:
        map_camera(frames)
        self.check_source(frames)

    def fit(self, views: Sequence[MapImage], descriptors: np.ndarray, quiet: bool = True) -> None:
        quiet = quiet or self.quiet
        self.check_map_store()  # again: load_state may have set the store of a file
        # A fit that fails part-way leaves no map, not the old map with new settings.
        self.structure, self.compact, self.match_index, self.keyframe_index = (None,) * 4
        self.tracked.clear()  # poses of another map's frames
        self.camera = map_camera(views)
        source = self.check_source(views, depth_files=False)
        if source == "colmap" and self.image_scale != 1.0 and not quiet:
            print(
                f"note: refine=features on a COLMAP model's points with SIFT at "
                f"image_scale {self.image_scale:g}, a share chosen on depth and triangulated "
                "maps, not yet on COLMAP observations (full-size pixels, refine.radius_px); "
                "refine=features_colmap uses 1.0"
            )
        self.zscore = ZScore().fit(check_features(descriptors))
        self.points = self.zscore(check_features(descriptors))
        # The map is built, and queries solved, in the colour camera's poses; answers
        # go back to the sensor the dataset's poses describe (relocfw.core.sensor_poses).
        self.pose_to_colour = map_pose_to_colour(views, "refine=features")
        self.poses = [colour_pose(view.pose, self.pose_to_colour) for view in views]
        self.viewpoints = None  # the new map's, computed on first use
        map_views = [
            MapView(
                image=view.image,
                pose=pose,
                camera=view.camera,
                depth_path=view.depth_path,
                name=view.name,
                depth_units_per_metre=view.depth_units_per_metre,
                depth_camera=view.depth_camera,
                depth_to_colour=view.depth_to_colour,
            )
            for view, pose in zip(views, self.poses, strict=True)
        ]

        parameters = self.build_parameters(views)

        def build() -> StructureMap:
            scale = self.image_scale
            if source == "depth":
                return build_from_depth(
                    map_views, self.max_features, quiet=quiet, image_scale=scale
                )
            if source == "colmap":
                observations = [getattr(view, "observations", None) for view in views]
                return build_from_colmap_points(
                    map_views,
                    observations,
                    self.max_features,
                    quiet=quiet,
                    image_scale=scale,
                    **parameters,
                )
            return build_by_triangulation(
                map_views, self.max_features, quiet=quiet, image_scale=scale, **parameters
            )

        if self.cache_dir is None:
            structure = build()
        else:
            key = structure_key(
                [v.name for v in views],
                self.poses,
                [v.camera for v in views],
                self.settings(views, parameters),
                [(v.depth_camera, v.depth_to_colour) for v in views],
            )
            structure = cached_structure_map(self.cache_dir, key, build, quiet)
        self.skipped = tuple(structure.skipped_views)
        if source != "triangulated" and not structure.point_counts().any():
            # Every query would fall back: a configuration that cannot work.
            if source == "colmap":
                raise ConfigError(
                    f"refine=features found no keypoint within {self.radius_px:g} px of a "
                    f"COLMAP observation in any of the {len(views)} map images (first: "
                    f"{self.skipped_views[0].name}: {self.skipped_views[0].reason}); are "
                    "the images the ones the model was made from, at its resolution?"
                )
            raise ConfigError(
                f"refine=features found no usable depth in any of the {len(views)} map "
                f"images (first: {self.skipped_views[0].name}: "
                f"{self.skipped_views[0].reason}); {NO_DEPTH_HINT}"
            )
        if self.map_store == "compact":
            # Only the folder's mapped arrays stay: the StructureMap is dropped here.
            self.compact = cached_compact_map(self.cache_dir, key, structure, quiet)
        else:
            self.structure = structure
            self.match_index = MatchIndex.of(structure, self.match_points_only)
        self.keyframe_index = self.keyframe_search_of(self.points)

    def keyframe_search_of(self, points: np.ndarray) -> FaissKeyframeSearch | None:
        """The faiss search over the z-scored map descriptors (keyframe_search=faiss);
        None: numpy's, over `self.points` itself."""
        return FaissKeyframeSearch(points) if self.keyframe_search == "faiss" else None

    @property
    def skipped_views(self) -> tuple:
        """The map images that gave no 3-D point (name and reason), for reports."""
        return self.skipped

    def check_fitted(self) -> None:
        """A ConfigError unless a map is fitted or loaded."""
        if self.structure is None and self.compact is None:
            raise ConfigError("the refiner is not fitted: fit the Relocalizer's map first")

    def state(self) -> dict[str, torch.Tensor]:
        """Everything a query uses, as plain tensors (relocfw.structure.map_state: every
        map image's uint8 descriptors, keypoints, the 3-D points of the keypoints that
        have one, poses and cameras; with map_store=compact the compact map's own
        arrays instead, relocfw.structure.compact_state), plus the standardisation and
        the z-scored map descriptors that keyframes are retrieved by, and the query
        options. A refiner loaded from it needs no map image, depth file or cache."""
        self.check_fitted()
        keys = (
            "keyframes",
            "map_store",
            "keyframe_search",
            "match_points_only",
            "rematch",
            "rematch_answer",
            *STATE_INTEGERS,
            *STATE_NUMBERS,
        )
        if self.compact is not None:
            stored_map = compact_state(self.compact)
        else:
            stored_map = map_state(self.structure)
        return {
            **stored_map,
            **self.zscore.state(),
            "keyframe_descriptors": torch.from_numpy(np.array(self.points, dtype=np.float64)),
            **options_state({key: getattr(self, key) for key in keys}),
            **pose_to_colour_state(self.pose_to_colour),
        }

    def load_state(self, state: dict[str, torch.Tensor]) -> None:
        """What `state` returned: the refiner is then fitted. Every tensor is checked
        before anything is kept (a model file is data from anyone); a fault is one
        DataError naming the tensor."""
        options = stored_options(state)
        # Files written before these options matched every keypoint of a map whose
        # SIFT ran at full size, held in memory, keyframes searched with numpy; that
        # is how they answer.
        options.setdefault("image_scale", 1.0)
        options.setdefault("match_points_only", False)
        options.setdefault("ransac_min_iterations", POSELIB_MIN_ITERATIONS)
        options.setdefault("map_store", "memory")
        options.setdefault("keyframe_search", "numpy")
        options.setdefault("rematch", "none")
        options.setdefault("rematch_answer", "second")
        structure, compact = None, None
        if options["map_store"] == "compact":
            if not options["match_points_only"]:
                raise DataError(
                    f"{STATE_LABEL}: match_points_only must be 1 with map_store compact "
                    "(a compact map keeps only keypoints with a 3-D point)"
                )
            compact = compact_of_state(state, STATE_LABEL)
            count, source = len(compact), compact.source
            poses = [compact.pose(i) for i in range(count)]
            cameras = {tuple(row) for row in compact.cameras.tolist()}
            camera = compact.camera(0) if len(cameras) == 1 and count else None
        else:
            if holds_compact_map(state):
                raise DataError(
                    f"{STATE_LABEL}: compact_ tensors belong to map_store compact, and "
                    "map_store is memory"
                )
            structure = map_of_state(state, STATE_LABEL)
            count, source, poses = len(structure), structure.source, list(structure.poses)
            distinct = set(structure.cameras)
            camera = distinct.pop() if len(distinct) == 1 else None
        keyframe_points, zscore = stored_keyframe_descriptors(state, count)
        pose_to_colour = stored_pose_to_colour(state, STATE_LABEL)
        # Built before anything is kept: an empty map is refused here, not half-loaded.
        keyframe_index = None
        if options["keyframe_search"] == "faiss":
            keyframe_index = FaissKeyframeSearch(keyframe_points)
        for key, value in options.items():
            setattr(self, key, value)
        self.structure, self.compact = structure, compact
        self.skipped = ()  # a model file keeps no skipped views (a query reads none)
        self.pose_to_colour = pose_to_colour
        self.match_index = None
        if structure is not None:
            self.match_index = MatchIndex.of(structure, self.match_points_only)
        self.zscore = zscore
        self.points = keyframe_points
        self.keyframe_index = keyframe_index
        self.poses = poses
        self.viewpoints = None
        self.camera = camera
        self.structure_source = source
        self.tracked.clear()

    def reset(self) -> None:
        """Forget every stream's last confident pose (keyframes=track)."""
        self.tracked.clear()

    def prior_of(self, query: RefineQuery) -> Pose | None:
        """The pose the first attempt's keyframes are chosen near; None: by descriptor."""
        if self.keyframes == "pose":
            return query.network_pose
        if self.keyframes == "track":
            return self.tracked.prior(query.name)
        return None

    def keyframes_of(self, query: RefineQuery) -> list[int]:
        """The keyframes of the query's first attempt."""
        return self.keyframes_near(query, self.prior_of(query))

    def keyframes_near(self, query: RefineQuery, prior: Pose | None) -> list[int]:
        """The `count` keyframes near `prior`; without one, by the query's descriptor."""
        count = min(self.count, len(self.poses))
        if prior is not None:
            # The map's poses are the colour camera's; the prior is the dataset's sensor's.
            prior = colour_pose(prior, self.pose_to_colour)
            if self.viewpoints is None:  # once per map, and only where poses choose
                self.viewpoints = MapViewpoints.of(self.poses)
            return list(keyframes_by_pose(self.viewpoints, prior, count))
        if self.keyframe_index is not None:
            return self.keyframe_index.nearest(self.zscore, query.descriptor, count)
        return keyframes_by_descriptor(self.zscore, self.points, query.descriptor, count)

    def refine(self, query: RefineQuery) -> Refined:
        self.check_fitted()
        camera = query_camera("refine=features", query.camera, self.camera)
        if self.keyframes == "pose" and not query.network_pose.is_finite:
            # No map image is near a NaN pose; the network's answer stands, flagged.
            return Refined(query.network_pose, 0.0, True, {"retrieval": 0.0})
        prior = self.prior_of(query)
        # The query's matches per keyframe, shared by its solves: a keyframe in both a
        # first and a second keyframe set is matched once.
        known = KnownMatches()
        refined, features, keyframes = self.attempt(query, camera, prior, known=known)
        if self.keyframes != "track":
            return self.rematched(query, camera, refined, features, keyframes, known)
        if refined.fell_back and prior is not None:
            # The track is lost on this frame: the same query again, by retrieval.
            started = time.perf_counter()
            retry, _, keyframes = self.attempt(query, camera, None, features, known=known)
            seconds = dict(refined.seconds)
            for part, spent in retry.seconds.items():
                seconds[part] = seconds.get(part, 0.0) + spent
            seconds["tracking_retry"] = time.perf_counter() - started
            refined = Refined(retry.pose, retry.confidence, retry.fell_back, seconds)
        refined = self.rematched(query, camera, refined, features, keyframes, known)
        self.tracked.record(query.name, refined.pose, refined.fell_back)
        return refined

    def rematched(
        self,
        query: RefineQuery,
        camera: PinholeCamera,
        first: Refined,
        features: LocalFeatures | None,
        first_keyframes: list[int],
        known: KnownMatches | None = None,
    ) -> Refined:
        """With refine.rematch, the query solved again against the keyframes nearest
        its first answer (with `first_keyframes` for union; the query's features
        reused); that answer where it succeeds (and, with rematch_answer=more_inliers,
        has at least the first's inliers), else the first. Its seconds add both
        solves per part, succeeded or not, the second's whole time in "rematch" too.
        Where the second keyframes are the first's, the first answer stands unsolved
        again (the same matches would be solved twice)."""
        if self.rematch == "none" or first.fell_back:
            return first
        started = time.perf_counter()
        keyframes = self.keyframes_near(query, first.pose)
        if self.rematch == "union":
            keyframes = list(dict.fromkeys([*first_keyframes, *keyframes]))
        chosen = time.perf_counter() - started
        seconds = dict(first.seconds)
        seconds["retrieval"] = seconds.get("retrieval", 0.0) + chosen  # by pose, above
        if set(keyframes) == set(first_keyframes):
            seconds["rematch"] = time.perf_counter() - started
            return Refined(first.pose, first.confidence, False, seconds)
        second, _, _ = self.attempt(query, camera, None, features, keyframes, known)
        for part, spent in second.seconds.items():
            seconds[part] = seconds.get(part, 0.0) + spent
        seconds["rematch"] = time.perf_counter() - started
        answer = first if second.fell_back or not self.second_answers(first, second) else second
        return Refined(answer.pose, answer.confidence, False, seconds)

    def second_answers(self, first: Refined, second: Refined) -> bool:
        """Whether a second solve that succeeded answers instead of the first (both
        confidences are inlier counts, one per query keypoint)."""
        if self.rematch_answer == "more_inliers":
            return second.confidence >= first.confidence
        return True

    def attempt(
        self,
        query: RefineQuery,
        camera: PinholeCamera,
        prior: Pose | None,
        features: LocalFeatures | None = None,
        keyframes: list[int] | None = None,
        known: KnownMatches | None = None,
    ) -> tuple[Refined, LocalFeatures | None, list[int]]:
        """One solve against the keyframes near `prior` (None: by descriptor; or the
        map images `keyframes`, where given), the query's local features it used
        (`features`: extracted already, by an earlier attempt of the same query) and
        the keyframes (map image indices). `known`: the query's matches per keyframe
        from its earlier solves (with the map in memory; the compact store numbers a
        query's keyframes afresh for each solve, so there it is not used)."""
        started = time.perf_counter()
        if keyframes is None:
            keyframes = self.keyframes_near(query, prior)
        chosen = list(keyframes)
        retrieval = time.perf_counter() - started
        structure, match_index = self.structure, self.match_index
        if self.compact is not None:
            # Just the keyframes, read from the mapped folder (row k: keyframes[k]); all
            # their keypoints have a point, so matching them all is match_points_only.
            keyframes = list(dict.fromkeys(keyframes))  # repeats dropped, as below
            structure = self.compact.keyframe_map(keyframes)
            keyframes, match_index, known = list(range(len(keyframes))), None, None
        answer = localize_against(
            structure,
            query.image,
            camera,
            keyframes,
            max_features=self.max_features,
            ratio=self.ratio,
            max_error_px=self.max_error_px,
            min_inliers=self.min_inliers,
            query_features=features,
            image_scale=self.image_scale,
            match_index=match_index,
            min_iterations=self.ransac_min_iterations,
            known_matches=known,
        )
        seconds = {"retrieval": retrieval, **answer.seconds}
        if not answer.success:
            found = Refined(query.network_pose, float(answer.inliers), True, seconds)
        else:
            answered = reference_pose(answer.pose, self.pose_to_colour)
            found = Refined(answered, float(answer.inliers), False, seconds)
        return found, answer.query_features, chosen
