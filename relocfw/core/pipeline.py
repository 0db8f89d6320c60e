"""Relocalizer: backbone + similarity index + crop search, the one pipeline for all methods.

A query goes through six stages, each in a module of its own:

    strip     the image scaled for the network          relocfw.core.imaging.Strip
    search    which square crop is closest to the map   CropSearch.propose, core.search_loop
    rerank    shared or scout candidates re-scored      QueryWindows.rerank
    sample    the chosen crop's test-time samples       relocfw.core.sampled_answer
    pose      the network's pose of the chosen window   NetworkAnswers
    refine    the final pose (retrieval, features)      PoseRefiner (relocfw.core.refinement)

Every network pass and map lookup goes through one Scorer (relocfw.core.scorer); the
options are one QueryOptions value (relocfw.core.query_options).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
import torch

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.imaging import check_aspect, check_rgb_image, check_rgb_images
from relocfw.core.interfaces import Backbone, CropSearch, SimilarityIndex
from relocfw.core.network_answers import NetworkAnswers
from relocfw.core.query_options import QueryOptions
from relocfw.core.query_windows import QueryWindows
from relocfw.core.refinement import MapImage, PoseRefiner, RefineQuery
from relocfw.core.sampled_answer import sampled_answer, samples_answer
from relocfw.core.sampling import configured_samples
from relocfw.core.scorer import Scorer
from relocfw.core.search_loop import score_chosen_together, search_together
from relocfw.core.trust_signal import with_bounds
from relocfw.core.values import Crop, CropWithPose, Localization, Pose

if TYPE_CHECKING:
    from relocfw.core.error_bounds import ErrorBounds


def check_sampling(
    crop_samples: int, mc_samples: int, crop_scale: float, refiner: PoseRefiner | None = None
) -> None:
    """Raise ConfigError for sampling options that cannot mean anything.

    `crop_scale` is the model's (train.crop_scale): at 1 the window fills the crop.
    A refiner that replaces the network's pose (retrieval) would throw the samples'
    mean away and answer with a pose their spread does not describe.
    """
    if crop_samples < 0:
        raise ConfigError(f"crop_samples must be >= 0, got {crop_samples}")
    replaces = bool(getattr(refiner, "replaces_network_pose", False))
    if replaces and (crop_samples > 0 or mc_samples > 0):
        raise ConfigError(
            f"the refiner {type(refiner).__name__} never answers with the network's pose, "
            f"but query.crop_samples={crop_samples} / backbone.mc_samples={mc_samples} "
            "sample that pose: use one or the other"
        )
    if crop_samples > 0 and crop_scale <= 1.0:
        raise ConfigError(
            f"crop_samples={crop_samples} draws random windows inside the chosen crop, but "
            f"the model's crop_scale is {crop_scale:g}: the window fills the crop and every "
            "sample would be the same window (train with train.crop_scale > 1)"
        )


def check_options(
    options: QueryOptions,
    backbone: Backbone,
    index: SimilarityIndex,
    crop_scale: float,
    refiner: PoseRefiner | None = None,
    search: CropSearch | None = None,
) -> None:
    """The checks of `options` that need the parts they run with (ConfigError); the
    CLI runs them before training, the Relocalizer when it is built."""
    if options.scoring == "shared" and not backbone.shares_strip:
        raise ConfigError(
            f"scoring=shared needs a backbone with feature_maps and describe_pooled; "
            f"{type(backbone).__name__} lacks them (use scoring=plain)"
        )
    if options.scoring == "scout" and (why := backbone.scout_refusal()) is not None:
        raise ConfigError(f"scoring=scout: {why}")
    check_sampling(options.crop_samples, configured_samples(backbone), crop_scale, refiner)
    if search is not None and search.sees_answers:
        check_search_sees_answers(options, backbone, search)


def check_search_sees_answers(
    options: QueryOptions, backbone: Backbone, search: CropSearch
) -> None:
    """A search that chooses by every window's answer (CropSearch.sees_answers) needs
    each window's pose, which only plain scoring computes, and answers from all of them,
    so sampling the chosen window alone would mean nothing."""
    samples = configured_samples(backbone)
    if options.crop_samples > 0 or samples > 0:
        raise ConfigError(
            f"the crop search {type(search).__name__} answers from every window's "
            f"pose; query.crop_samples={options.crop_samples} / backbone.mc_samples="
            f"{samples} would sample the chosen window alone: use one or the other"
        )
    if options.scoring != "plain":
        raise ConfigError(
            f"the crop search {type(search).__name__} chooses by every crop's network "
            f"answer, which scoring={options.scoring} does not compute: use scoring=plain"
        )


class Relocalizer:
    """Fits the map from training images and localizes query images.

    A plain object: it is built from instances, never from a config, so a script or
    a notebook uses it as the CLI does.

    Args:
        backbone: trained network; put in eval mode here.
        index: the map, fitted by `fit`.
        search: the crop search strategy.
        options: how a query is localized (relocfw.core.query_options.QueryOptions).
        device: where the network runs.
        refiner: the last stage (relocfw.core.refinement.PoseRefiner), e.g. the
            nearest map images' poses (retrieval) or local features + PnP; None: the
            network's pose is the answer.

    Candidate crops and the map are always scored by the dropout-free network; only
    the chosen crop is sampled (backbone.mc_samples, options.crop_samples), once.

    One call at a time: sampling sets the backbone's sample count and torch's random
    stream for its duration, so two threads must not localize with one Relocalizer
    (`localize_many` runs many queries on the calling thread, starting no other).

    Example:
        >>> search = GeneticCropSearch()  # doctest: +SKIP
        >>> relocalizer = Relocalizer(backbone, KMeansIndex(k=40), search)  # doctest: +SKIP
        >>> relocalizer.fit(train_images, train_poses)  # doctest: +SKIP
        >>> relocalizer.localize(image).pose  # doctest: +SKIP
    """

    def __init__(
        self,
        backbone: Backbone,
        index: SimilarityIndex,
        search: CropSearch,
        options: QueryOptions | None = None,
        device: str | torch.device = "cpu",
        refiner: PoseRefiner | None = None,
    ) -> None:
        options = QueryOptions() if options is None else options
        if not isinstance(options, QueryOptions):
            raise ConfigError(f"options must be a QueryOptions, got {type(options).__name__}")
        self.scorer = Scorer(backbone, index, device, options.batch_size)
        check_options(options, backbone, index, self.scorer.crop_scale, refiner, search)
        self.options = options
        self.search = search
        self.refiner = refiner
        self.map_poses: list[Pose] = []
        self.metadata: dict = {}  # what a model file says about the data it was built on
        # Calibrated error bounds (relocfw.report.calibration), given to every answer;
        # None: answers carry NaN bounds.
        self.bounds: ErrorBounds | None = None

    @property
    def backbone(self) -> Backbone:
        return self.scorer.backbone

    @property
    def index(self) -> SimilarityIndex:
        return self.scorer.index

    @property
    def device(self) -> torch.device:
        return self.scorer.device

    @property
    def crop_scale(self) -> float:
        """The backbone's training crop_scale (relocfw.core.scorer.Scorer.crop_scale)."""
        return self.scorer.crop_scale

    def replace(
        self,
        backbone: Backbone | None = None,
        options: QueryOptions | None = None,
        search: CropSearch | None = None,
    ) -> Relocalizer:
        """This pipeline with another network answering for the same one (e.g. its ONNX
        export), other options and/or another search: the same fitted map, map poses,
        metadata (and error bounds, unless `options` or `search` change). The refiner
        is the same object too, history included (a sequence refiner's frames of each
        recording): query one of the two pipelines, or call `refiner.reset()` before
        switching, as evaluation does."""
        swapped = Relocalizer(
            backbone or self.backbone,
            self.index,
            search or self.search,
            options or self.options,
            self.device,
            self.refiner,
        )
        swapped.map_poses = self.map_poses
        swapped.metadata = self.metadata
        # Other options or another search give other answers than the bounds were
        # calibrated on; another network answering for the same one (an engine) not.
        same_answers = options in (None, self.options) and search in (None, self.search)
        swapped.bounds = self.bounds if same_answers else None
        return swapped

    def with_backbone(self, backbone: Backbone) -> Relocalizer:
        """`replace(backbone=backbone)`."""
        return self.replace(backbone=backbone)

    def describe(self, images: Sequence[np.ndarray], quiet: bool = True) -> np.ndarray:
        """[N, D] descriptors of the centre crops: what the map is built from.

        Raises:
            DataError: an image is not H x W x 3 uint8 RGB (naming its index).
        """
        return self.scorer.describe(images, quiet)

    def fit(
        self,
        images: Sequence[np.ndarray],
        poses: Sequence[Pose] | None = None,
        quiet: bool = True,
        frames: Sequence[object] | None = None,
    ) -> np.ndarray:
        """Build the map from training images (and their poses, for the refiner and
        model files).

        Args:
            frames: per image, what the refiner may use of it: objects with `name`,
                `camera`, `depth_path`, `depth_units_per_metre`, `depth_camera`,
                `depth_to_colour`, `pose_to_colour` and `observations` (a COLMAP
                model's 3-D points),
                such as the dataset's relocfw.data.frames.Frame (a missing attribute:
                unknown).

        Returns:
            The [N, D] training descriptors.

        Raises:
            DataError: an image is not H x W x 3 uint8 RGB (naming its index), or
                the refiner lacks poses, or a per-image list is short.
        """
        needs_poses = self.refiner is not None
        if needs_poses and (poses is None or len(poses) != len(images)):
            raise DataError(
                "refinement (e.g. retrieval) needs the pose of every map image: fit(images, poses)"
            )
        features = self.describe(images, quiet=quiet)
        self.index.fit(features)
        self.map_poses = list(poses) if poses is not None else []
        if self.search.wants_map:
            if len(self.map_poses) != len(images):
                raise DataError(
                    f"the crop search {type(self.search).__name__} needs the pose of every "
                    "map image: fit(images, poses)"
                )
            scale = self.scorer.distance_scale(features)
            self.search.fit_map(features, self.map_poses, scale)
        if self.refiner is not None:
            views = map_images(images, self.map_poses, frames)
            self.refiner.fit(views, features, quiet=quiet)
        return features

    def localize(
        self, image: np.ndarray, camera: PinholeCamera | None = None, name: str | None = None
    ) -> Localization:
        """Pose of one RGB image (H x W x 3 uint8) through the crop search.

        Args:
            camera: the image's intrinsics, for a refiner; None: the map's camera.
            name: the image's frame name, for a refiner that reads the recording
                (refine=sequence: "seq-03/frame-000042"); None: unknown.

        Raises:
            DataError: the image is of another type or shape (e.g. float, RGBA), is
                thinner than query.max_aspect allows, or its crop search asks for
                more windows than query.max_candidates.
        """
        check_rgb_image(image)
        limits = (self.options.max_aspect, self.options.max_candidates)
        query = QueryWindows(image, self.scorer, self.options.scoring, *limits)  # strip
        (crop,) = search_together(self.search, [query])  # search
        return self.answer(query, crop, camera=camera, name=name)

    def answer(
        self,
        query: QueryWindows,
        crop: Crop,
        seconds: float | None = None,
        camera: PinholeCamera | None = None,
        name: str | None = None,
    ) -> Localization:
        """The Localization of a query's chosen crop: rerank -> sample -> pose -> refine.

        Args:
            seconds: the query's time when the caller measures it (`localize_many`
                shares a group's time among its queries); default: since the strip.
            camera: the query's intrinsics, for the refiner (None: the map's).
            name: the query's frame name, for the refiner (None: unknown).
        """
        crop = query.rerank(crop, self.options.rerank)
        distance, answer = query.answer_of(crop)
        passes = query.network_passes()
        if samples_answer(self.scorer, self.options.crop_samples):
            streams = (self.options.sample_seed, query.query_seed)
            answer, sampled = sampled_answer(
                self.scorer, query.strip, crop, answer, self.options.crop_samples, streams
            )
            passes += sampled
        pose, refined = self.pose_of(answer), None
        if isinstance(crop, CropWithPose):  # the search answered a pose of its own
            pose, crop = crop.pose, crop.plain()
        if self.refiner is not None:
            refined = self.refiner.refine(
                RefineQuery(query.image, pose, answer.features, camera, name)
            )
            pose = refined.pose
        localization = Localization(
            pose=pose,
            crop=crop,
            distance=distance,
            evaluations=query.evaluations,
            seconds=time.perf_counter() - query.started if seconds is None else seconds,
            position_spread=float(answer.position_spread),
            orientation_spread_deg=float(answer.orientation_spread_deg),
            network_passes=passes,
            refine_confidence=float("nan") if refined is None else float(refined.confidence),
            fell_back=refined is not None and refined.fell_back,
            refine_seconds=dict(refined.seconds) if refined is not None else {},
        )
        return localization if self.bounds is None else with_bounds(localization, self.bounds)

    def pose_of(self, answer: NetworkAnswers) -> Pose:
        """The network's pose for one window: what the refiner starts from (and the
        answer without one). The crop-premise diagnostic scores every window by it."""
        return Pose(answer.positions, answer.quaternions)

    def localize_many(
        self,
        images: Sequence[np.ndarray],
        queries_at_once: int | None = None,
        cameras: Sequence[PinholeCamera | None] | None = None,
        names: Sequence[str | None] | None = None,
    ) -> list[Localization]:
        """Poses of many images, `queries_at_once` (default: the options') searched
        together: their plain windows go through shared forward passes (at most
        `batch_size` windows each) in one loop on this thread (relocfw.core.search_loop).

        Each query's search runs as in `localize` (its own random stream, its own
        windows), so the answers are `localize`'s; only the network calls are merged.
        A query's `seconds` is its group's time shared equally among its queries.
        `cameras`: each image's intrinsics, for a refiner (None: the map's camera).
        `names`: each image's frame name, for a refiner that reads recordings; the
        answers are given in the images' order, so a recording's queries reach the
        refiner in the order they are listed.

        Raises:
            DataError: an image is not H x W x 3 uint8 RGB or is thinner than
                query.max_aspect allows (naming its index), before any query runs; a
                search asks for more windows than query.max_candidates.
        """
        check_rgb_images(images)
        for number, image in enumerate(images):  # every shape before any query runs
            height, width = image.shape[:2]
            check_aspect(width, height, f"image {number} is", self.options.max_aspect)
        size = self.options.replace(queries_at_once=queries_at_once).queries_at_once
        cameras = [None] * len(images) if cameras is None else list(cameras)
        if len(cameras) != len(images):
            raise DataError(f"{len(images)} images but {len(cameras)} cameras")
        names = [None] * len(images) if names is None else list(names)
        if len(names) != len(images):
            raise DataError(f"{len(images)} images but {len(names)} names")
        answers: list[Localization] = []
        for start in range(0, len(images), size):
            group, group_cameras = images[start : start + size], cameras[start : start + size]
            group_names = names[start : start + size]
            if len(group) == 1:
                answers.append(self.localize(group[0], group_cameras[0], group_names[0]))
                continue
            started = time.perf_counter()
            limits = (self.options.max_aspect, self.options.max_candidates)
            queries = [QueryWindows(i, self.scorer, self.options.scoring, *limits) for i in group]
            crops = search_together(self.search, queries)
            score_chosen_together(queries, crops, self.options.rerank)
            found = [
                self.answer(q, c, camera=camera, name=name)
                for q, c, camera, name in zip(
                    queries, crops, group_cameras, group_names, strict=True
                )
            ]
            seconds = (time.perf_counter() - started) / len(group)
            answers += [dataclasses.replace(a, seconds=seconds) for a in found]
        return answers


def map_images(
    images: Sequence[np.ndarray], poses: Sequence[Pose], frames: Sequence[object] | None
) -> list[MapImage]:
    """The refiner's view of the map images; DataError when `frames` does not have one
    entry per image."""
    if frames is not None and len(frames) != len(images):
        raise DataError(f"fit: {len(images)} images but {len(frames)} frames")
    frames = [None] * len(images) if frames is None else list(frames)
    return [
        MapImage(
            name=getattr(frame, "name", f"map image {i}"),
            image=image,
            pose=pose,
            camera=getattr(frame, "camera", None),
            depth_path=getattr(frame, "depth_path", None),
            depth_units_per_metre=getattr(frame, "depth_units_per_metre", 1000.0),
            observations=getattr(frame, "observations", None),
            depth_camera=getattr(frame, "depth_camera", None),
            depth_to_colour=getattr(frame, "depth_to_colour", None),
            pose_to_colour=getattr(frame, "pose_to_colour", None),
        )
        for i, (image, pose, frame) in enumerate(zip(images, poses, frames, strict=True))
    ]
