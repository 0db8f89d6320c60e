"""Relocalizer: backbone + similarity index + crop search, the one pipeline for all methods."""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial

import numpy as np
import torch
from threadpoolctl import ThreadpoolController

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import mean_quaternion
from relocfw.core.imaging import Strip, check_rgb_image, check_rgb_images, to_network_input
from relocfw.core.interfaces import (
    Backbone,
    CropSearch,
    SimilarityIndex,
    crop_at,
    crop_side_and_span,
)
from relocfw.core.lockstep import INTERRUPTED_JOIN_SECONDS, Lockstep, first_failure, join_within
from relocfw.core.network_answers import NetworkAnswers, as_numpy
from relocfw.core.progress import Progress
from relocfw.core.query_run import QueryRun
from relocfw.core.sampling import (
    combine_samples,
    configured_samples,
    monte_carlo,
    query_streams,
    random_windows,
    sample_share,
    seeded_torch,
)
from relocfw.core.values import Crop, Localization, Pose
from relocfw.core.window_pooling import StripMaps

SCORINGS = ("plain", "shared")


@dataclass(frozen=True)
class WindowScores:
    """Every crop offset of one query: its window, map distance and pose.

    What `Relocalizer.score_windows` returns: entry i is offset i along the long axis
    (crop=sweep at stride 1 tries exactly these), so a study of the crop premise sees
    the very windows, distances and poses the pipeline would produce.
    """

    crops: tuple[Crop, ...]  # [n] in original image pixels, as Localization.crop
    corners: np.ndarray  # [n, 2] int (y, x) of each offset's window in the strip
    distances: np.ndarray  # [n] map distance of each window's descriptor
    positions: np.ndarray  # [n, 3] the pose answered were that crop chosen
    quaternions: np.ndarray  # [n, 4]
    centre: int  # the entry of the centre crop (crop=centre, and the map's descriptors)
    windows: int  # distinct windows, i.e. network inputs run: offsets may share one
    scale: float  # strip pixels per original image pixel
    input_size: int  # the window's side in strip pixels

    def views(self) -> np.ndarray:
        """[n, 3] (x, y, side) in original pixels of what the network sees of each crop.

        The whole crop when crop_scale is 1; its central 1/crop_scale otherwise.
        """
        side = np.full(len(self.crops), self.input_size / self.scale)
        return np.column_stack(
            [self.corners[:, 1] / self.scale, self.corners[:, 0] / self.scale, side]
        )


def check_retrieval(index: SimilarityIndex, retrieval_k: int) -> None:
    """Retrieval answers with map images' poses: the index must name its neighbours."""
    if retrieval_k > 0 and not hasattr(index, "neighbours"):
        raise ConfigError(
            f"retrieval_k={retrieval_k} needs an index that returns neighbours "
            f"(index=exhaustive); {type(index).__name__} does not"
        )


def check_sampling(retrieval_k: int, crop_samples: int, mc_samples: int, crop_scale: float) -> None:
    """Raise ConfigError for sampling options that cannot mean anything.

    `crop_scale` is the model's (train.crop_scale): at 1 the window fills the crop.
    """
    if crop_samples < 0:
        raise ConfigError(f"crop_samples must be >= 0, got {crop_samples}")
    if crop_samples > 0 and crop_scale <= 1.0:
        raise ConfigError(
            f"crop_samples={crop_samples} draws random windows inside the chosen crop, but "
            f"the model's crop_scale is {crop_scale:g}: the window fills the crop and every "
            "sample would be the same window (train with train.crop_scale > 1)"
        )
    if retrieval_k > 0 and (crop_samples > 0 or mc_samples > 0):
        raise ConfigError(
            "retrieval_k > 0 answers with map images' poses, but crop_samples / "
            "backbone.mc_samples sample the network's pose: use one or the other"
        )


def check_rerank(rerank: int, scoring: str) -> int:
    """`rerank` as an int, or ConfigError when it cannot apply."""
    if int(rerank) != rerank or rerank < 1:
        raise ConfigError(f"rerank must be an integer >= 1, got {rerank!r}")
    if rerank > 1 and scoring != "shared":
        raise ConfigError(
            f"rerank={rerank} re-scores the best shared-scoring candidates plainly; "
            f"with scoring={scoring} every candidate is already plain (use scoring=shared)"
        )
    return int(rerank)


def check_scoring(scoring: str, backbone: Backbone) -> None:
    """Raise ConfigError unless `backbone` can score crops the way `scoring` names."""
    if scoring not in SCORINGS:
        raise ConfigError(f"scoring must be one of {', '.join(SCORINGS)}, got {scoring!r}")
    if scoring == "shared" and not backbone.shares_strip:
        raise ConfigError(
            f"scoring=shared needs a backbone with feature_maps and describe_pooled; "
            f"{type(backbone).__name__} lacks them (use scoring=plain)"
        )


class Relocalizer:
    """Fits the map from training images and localizes query images.

    A plain object: it is built from instances, never from a config, so a script or
    a notebook uses it as the CLI does.

    Args:
        backbone: trained network; put in eval mode here.
        index: the map, fitted by `fit`.
        crop: the crop search strategy.
        device: where the network runs.
        batch_size: most crops per forward pass.
        retrieval_k: 0 answers with the network's pose (PoseNet and the paper). k > 0
            answers with the distance-weighted mean pose of the k training images
            nearest to the chosen crop's descriptor: the image-retrieval baseline.
            Needs an index with `neighbours` (index=exhaustive) and training poses.
        scoring: how candidate crops are scored. "plain": each distinct window goes
            through the whole network (the paper). "shared": the trunk runs once over
            the whole strip and every candidate is pooled from its maps
            (relocfw.core.window_pooling); the chosen crop then goes through the plain path
            once, so the pose is the plain pose of that crop. Needs a backbone with
            `feature_maps` and `describe_pooled`.
        rerank: with scoring="shared", the `rerank` windows with the smallest shared
            distances (the search's choice among them) go through the plain network
            in one batch and the smallest plain distance chooses: the shared path
            only ranks. 1: the search's choice as it is.
        crop_samples: > 0 answers with the mean pose of this many random windows of
            the chosen crop (test-time crop sampling, relocfw.core.sampling); with the
            backbone's Monte Carlo dropout on, each window gets its own mask. Needs a
            model trained with crop_scale > 1 (else every window is the same).
        sample_seed: seeds the samples, mixed with each query image's fingerprint.
        queries_at_once: how many queries a list of images (relocfw.report.evaluation,
            task=localize) runs together through `localize_many`, their windows in
            shared forward passes; 1 localizes one at a time (each query's own
            latency in `seconds`).

    Candidate crops and the map are always scored by the dropout-free network; only
    the chosen crop is sampled (backbone.mc_samples, crop_samples), once.

    One call at a time: sampling sets the backbone's sample count and torch's random
    stream for its duration, so two threads must not localize with one Relocalizer
    (`localize_many` runs many queries safely).
    """

    def __init__(
        self,
        backbone: Backbone,
        index: SimilarityIndex,
        crop: CropSearch,
        device: str | torch.device = "cpu",
        batch_size: int = 16,
        retrieval_k: int = 0,
        scoring: str = "plain",
        crop_samples: int = 0,
        sample_seed: int = 0,
        rerank: int = 1,
        queries_at_once: int = 1,
    ) -> None:
        check_scoring(scoring, backbone)
        self.rerank = check_rerank(rerank, scoring)
        self.scoring = scoring
        self.device = torch.device(device)
        self.backbone = backbone.to(self.device).eval()
        self.memory_format = torch.contiguous_format
        if backbone.channels_last:
            self.memory_format = torch.channels_last
            self.backbone.to(memory_format=self.memory_format)
        self.index = index
        self.crop = crop
        self.batch_size = int(batch_size)
        self.retrieval_k = int(retrieval_k)
        check_retrieval(index, self.retrieval_k)
        if int(queries_at_once) != queries_at_once or queries_at_once < 1:
            raise ConfigError(f"queries_at_once must be an integer >= 1, got {queries_at_once!r}")
        self.queries_at_once = int(queries_at_once)
        self.crop_samples = int(crop_samples)
        if int(sample_seed) != sample_seed or sample_seed < 0:
            raise ConfigError(f"sample_seed must be an integer >= 0, got {sample_seed!r}")
        self.sample_seed = int(sample_seed)
        check_sampling(
            self.retrieval_k, self.crop_samples, configured_samples(backbone), self.crop_scale
        )
        self._threadpools: ThreadpoolController | None = None  # found on first query
        self._cells: int | None = None  # see _window_cells
        self._sample_share: float | None = None  # see _sampled_passes
        self.map_poses: list[Pose] = []
        self.metadata: dict = {}  # what a model file says about the data it was built on

    def with_backbone(self, backbone: Backbone) -> Relocalizer:
        """This pipeline with another network answering for the same one (e.g. its ONNX
        export): the same fitted map, crop search, options and metadata."""
        swapped = Relocalizer(
            backbone,
            self.index,
            self.crop,
            self.device,
            self.batch_size,
            self.retrieval_k,
            self.scoring,
            crop_samples=self.crop_samples,
            sample_seed=self.sample_seed,
            rerank=self.rerank,
            queries_at_once=self.queries_at_once,
        )
        swapped.map_poses = self.map_poses
        swapped.metadata = self.metadata
        return swapped

    @property
    def crop_scale(self) -> float:
        """The backbone's training crop_scale: the network sees the central
        1/crop_scale of every crop (relocfw.core.imaging.Strip), the field of view of its
        training crops; 1.0 sees the whole crop."""
        return float(self.backbone.crop_scale)

    @torch.inference_mode()
    def _forward(self, inputs: torch.Tensor, samples: int = 0) -> NetworkAnswers:
        """Network answers for uint8 inputs, in batches of at most `batch_size`.

        `samples` Monte Carlo dropout masks per input; 0 (scoring, the map) runs the
        dropout-free network whatever the backbone is configured to sample.
        """
        with monte_carlo(self.backbone, samples):
            return self._forward_batches(inputs)

    def _forward_batches(self, inputs: torch.Tensor) -> NetworkAnswers:
        parts = []
        for start in range(0, len(inputs), self.batch_size):
            batch = to_network_input(inputs[start : start + self.batch_size].to(self.device))
            batch = batch.contiguous(memory_format=self.memory_format)
            out = self.backbone(batch)
            n = len(batch)
            parts.append(
                NetworkAnswers(
                    as_numpy(out.positions, n),
                    as_numpy(out.quaternions, n),
                    as_numpy(out.features, n),
                    as_numpy(out.position_spread, n),
                    as_numpy(out.orientation_spread_deg, n),
                )
            )
        return NetworkAnswers(*(np.concatenate(column) for column in zip(*parts, strict=True)))

    def describe(self, images: Sequence[np.ndarray], quiet: bool = True) -> np.ndarray:
        """[N, D] descriptors of the centre crops: what the map is built from.

        Raises:
            DataError: an image is not H x W x 3 uint8 RGB (naming its index).
        """
        check_rgb_images(images)
        size = self.backbone.input_size
        progress = Progress(len(images), "describing map images", quiet=quiet)
        features = []
        for start in range(0, len(images), self.batch_size):
            strips = [
                Strip(image, size, self.crop_scale)
                for image in images[start : start + self.batch_size]
            ]
            batch = torch.stack([s.cut(s.window(s.centre_crop())) for s in strips])
            features.append(self._forward(batch).features)
            progress.advance(len(strips))
        progress.close()
        return np.concatenate(features)

    def fit(
        self,
        images: Sequence[np.ndarray],
        poses: Sequence[Pose] | None = None,
        quiet: bool = True,
    ) -> np.ndarray:
        """Build the map from training images (and their poses, for retrieval).

        Returns:
            The [N, D] training descriptors.

        Raises:
            DataError: an image is not H x W x 3 uint8 RGB (naming its index), or
                retrieval lacks poses.
        """
        if self.retrieval_k > 0 and (poses is None or len(poses) != len(images)):
            raise DataError("retrieval needs the pose of every map image: fit(images, poses)")
        features = self.describe(images, quiet=quiet)
        self.index.fit(features)
        self.map_poses = list(poses) if poses is not None else []
        return features

    def _one_blas_thread(self) -> ThreadpoolController:
        """Run map queries on one BLAS thread.

        A query's index lookups are small. A multi-threaded BLAS call leaves its
        workers spinning afterwards, competing with the network's threads for the
        same cores: on 2 cores it nearly doubled the sweep's time per query.
        """
        if self._threadpools is None:
            self._threadpools = ThreadpoolController()
        return self._threadpools.limit(limits=1, user_api="blas")

    def _map_distance(self, features: np.ndarray) -> np.ndarray:
        # localize_many makes every lookup on its serving thread, so no lock is needed.
        with self._one_blas_thread():
            return self.index.distance(features)

    def _retrieved_pose(self, features: np.ndarray) -> Pose:
        with self._one_blas_thread():
            distances, indices = self.index.neighbours(features[None], self.retrieval_k)
        weights = 1.0 / (distances[0] + 1e-6)
        weights /= weights.sum()
        poses = [self.map_poses[i] for i in indices[0]]
        position = np.sum([w * p.position for w, p in zip(weights, poses, strict=True)], axis=0)
        quaternion = mean_quaternion(np.stack([p.quaternion for p in poses]), weights)
        return Pose(position, quaternion)

    def _score_corners(
        self, strip: Strip, corners: Sequence[tuple[int, int]]
    ) -> tuple[np.ndarray, NetworkAnswers]:
        """Map distances and network answers of strip windows (scoring=plain).

        The one place a window becomes a distance: `localize` and `score_windows`
        share it, so the diagnostic measures what the search sees.
        """
        answers = self._forward(torch.stack([strip.cut(c) for c in corners]))
        return self._map_distance(answers.features), answers

    def _answer_pose(self, answer: NetworkAnswers) -> Pose:
        """The pose answered for one window: the network's, or retrieval's."""
        if self.retrieval_k > 0:
            return self._retrieved_pose(answer.features)
        return Pose(answer.positions, answer.quaternions)

    @torch.inference_mode()
    def _strip_maps(self, strip: Strip) -> StripMaps:
        """The trunk's maps of the whole strip: one pass for every candidate window."""
        pixels = to_network_input(strip.pixels[None].to(self.device))
        pixels = pixels.contiguous(memory_format=self.memory_format)
        maps = self.backbone.feature_maps(pixels)[0]
        height, width = strip.pixels.shape[1:]
        return StripMaps(maps, height, width, self.backbone.input_size, self._window_cells())

    @torch.inference_mode()
    def _window_cells(self) -> int | None:
        """Cells of the trunk's maps that one input-sized window spans (crop_scale > 1).

        With crop_scale 1 a window spans the strip's whole short side, so StripMaps
        knows it; otherwise the maps of one blank input tell, measured once.
        """
        if self.crop_scale == 1.0:
            return None
        if self._cells is None:
            side = self.backbone.input_size
            blank = torch.zeros(1, 3, side, side, device=self.device)
            self._cells = int(self.backbone.feature_maps(blank).shape[-1])
        return self._cells

    @torch.inference_mode()
    def _shared_features(self, maps: StripMaps, corners: list[tuple[int, int]]) -> np.ndarray:
        return self.backbone.describe_pooled(maps.pooled(corners)).double().cpu().numpy()

    def localize(self, image: np.ndarray) -> Localization:
        """Pose of one RGB image (H x W x 3 uint8) through the crop search.

        Raises:
            DataError: the image is of another type or shape (e.g. float, RGBA).
        """
        check_rgb_image(image)
        run = QueryRun(self, image, self._score_corners)
        run.choose()
        return run.answer()

    def localize_many(
        self, images: Sequence[np.ndarray], queries_at_once: int | None = None
    ) -> list[Localization]:
        """Poses of many images, the plain windows of `queries_at_once` queries scored
        in shared forward passes (at most `batch_size` windows each).

        Each query's search runs as in `localize` (its own random stream, its own
        windows), so the answers are `localize`'s; only the network calls are merged:
        the centre crops of a group go through in one batch, the GA's generations of
        the whole group together. A query's `seconds` is its group's time shared
        equally among the group's queries.

        Raises:
            DataError: an image is not H x W x 3 uint8 RGB (naming its index), before
                any query runs.
        """
        check_rgb_images(images)
        if queries_at_once is None:
            queries_at_once = self.queries_at_once
        if int(queries_at_once) != queries_at_once or queries_at_once < 1:
            raise ConfigError(f"queries_at_once must be an integer >= 1, got {queries_at_once!r}")
        queries_at_once = int(queries_at_once)
        answers: list[Localization] = []
        for start in range(0, len(images), queries_at_once):
            answers += self._localize_group(images[start : start + queries_at_once])
        return answers

    def _localize_group(self, images: Sequence[np.ndarray]) -> list[Localization]:
        if len(images) == 1:
            return [self.localize(images[0])]
        started = time.perf_counter()
        lockstep = Lockstep(len(images), self._score_together)
        runs = [
            QueryRun(
                self, image, partial(self._ask, lockstep, member), partial(lockstep.call, member)
            )
            for member, image in enumerate(images)
        ]
        failures: dict[int, BaseException] = {}

        def search(member: int) -> None:
            try:
                runs[member].choose()
            except BaseException as error:  # noqa: BLE001 - re-raised below
                failures[member] = error
            finally:
                lockstep.leave(member)

        # Daemons: a thread that outlives the short join after an interrupt must not
        # keep the process alive.
        threads = [
            threading.Thread(target=search, args=(m,), daemon=True) for m in range(len(runs))
        ]
        started_threads = 0
        try:
            for thread in threads:
                thread.start()
                started_threads += 1
        finally:
            # Members that never started must not be waited for by those that did.
            for member in range(started_threads, len(runs)):
                lockstep.leave(member)
            try:
                lockstep.serve()  # every network pass on this thread (relocfw.core.lockstep)
            except BaseException:
                # Interrupted (Ctrl-C): serve has cancelled the members; their threads
                # end at their next network call, so give them a moment, then raise.
                join_within(threads[:started_threads], INTERRUPTED_JOIN_SECONDS)
                raise
            for thread in threads[:started_threads]:
                thread.join()
        if failures:
            raise first_failure(failures)
        # Sampling (dropout masks, seeded per query) runs here, one query at a time:
        # torch's random stream and the backbone's sample count are not per thread.
        answers = [run.answer() for run in runs]
        seconds = (time.perf_counter() - started) / len(runs)
        return [dataclasses.replace(answer, seconds=seconds) for answer in answers]

    @staticmethod
    def _ask(
        lockstep: Lockstep, member: int, strip: Strip, corners: list[tuple[int, int]]
    ) -> tuple[np.ndarray, NetworkAnswers]:
        return lockstep.ask(member, (strip, corners))

    def _score_together(
        self, requests: Sequence[tuple[Strip, list[tuple[int, int]]]]
    ) -> list[tuple[np.ndarray, NetworkAnswers]]:
        """Plain windows of several queries in one forward pass, split back."""
        windows = torch.stack([strip.cut(c) for strip, corners in requests for c in corners])
        answers = self._forward(windows)
        distances = self._map_distance(answers.features)
        split, start = [], 0
        for _, corners in requests:
            end = start + len(corners)
            part = NetworkAnswers(*(column[start:end] for column in answers))
            split.append((distances[start:end], part))
            start = end
        return split

    def _sampled_answer(
        self, strip: Strip, crop: Crop, plain: NetworkAnswers, fingerprint: int
    ) -> tuple[NetworkAnswers, float]:
        """The chosen crop's answer from its samples, and the extra network passes.

        `plain` is the crop's dropout-free answer: its descriptor, the one the index
        saw, stays the answer's descriptor.
        """
        windows_rng, torch_seed = query_streams(self.sample_seed, fingerprint)
        masks = configured_samples(self.backbone)
        with seeded_torch(torch_seed, self.device):
            if self.crop_samples == 0:
                window = strip.cut(strip.window(crop))[None]
                sampled = self._forward(window, masks)
                answer = NetworkAnswers(*(column[0] for column in sampled))
                return answer, self._sampled_passes(1, masks)
            corners = random_windows(strip, crop, self.crop_samples, windows_rng)
            windows = torch.stack([strip.cut(c) for c in corners])
            # With dropout on, one mask per window: every sample is a new crop and mask.
            masks = 1 if masks > 0 else 0
            samples = self._forward(windows, masks)
        position, quaternion, position_spread, orientation_spread = combine_samples(
            samples.positions, samples.quaternions
        )
        answer = NetworkAnswers(
            position,
            quaternion,
            plain.features,
            np.float64(position_spread),
            np.float64(orientation_spread),
        )
        return answer, self._sampled_passes(len(corners), masks)

    def _sampled_passes(self, windows: int, masks: int) -> float:
        """Network passes of sampling `windows` windows with `masks` dropout masks each,
        in whole-network passes: each window's pass counts one, each mask the share of
        a pass that a sample reruns (relocfw.core.sampling.sample_share: 0.0014 for
        PoseNet's kendall variant, 0.60 for "all"), so 40 kendall samples of one
        window cost 1.06 passes and 40 of "all" 25."""
        if masks == 0:
            return float(windows)
        if self._sample_share is None:  # measured once, in a random stream of its own
            self._sample_share = sample_share(self.backbone, self.device)
        return windows * (1.0 + masks * self._sample_share)

    @torch.inference_mode()
    def score_windows(self, image: np.ndarray) -> WindowScores:
        """Every crop offset of one RGB image with its map distance and pose.

        For studying the paper's premise (relocfw.report.diagnosis): the offsets are those
        crop=sweep tries at stride 1, cut as `localize` cuts them (crop_scale
        included), scored by the plain network whatever `scoring` says, and each pose
        is what `localize` answers were that crop chosen (retrieval included). Offsets
        that round to the same window share one network pass; windows go through the
        network `batch_size` at a time, so memory stays flat however long the image.

        Raises:
            DataError: the image is not H x W x 3 uint8 RGB.
        """
        check_rgb_image(image)
        strip = Strip(image, self.backbone.input_size, self.crop_scale)
        _, span = crop_side_and_span(strip.width, strip.height)
        crops = tuple(crop_at(offset, strip.width, strip.height) for offset in range(span + 1))
        corners = [strip.window(c) for c in crops]
        distinct = list(dict.fromkeys(corners))
        distances, positions, quaternions = [], [], []
        for start in range(0, len(distinct), self.batch_size):
            chunk_distances, answers = self._score_corners(
                strip, distinct[start : start + self.batch_size]
            )
            poses = [
                self._answer_pose(NetworkAnswers(*(column[i] for column in answers)))
                for i in range(len(chunk_distances))
            ]
            distances.append(np.asarray(chunk_distances, dtype=np.float64))
            positions += [p.position for p in poses]
            quaternions += [p.quaternion for p in poses]
        where = {corner: i for i, corner in enumerate(distinct)}
        index = np.array([where[c] for c in corners])
        return WindowScores(
            crops=crops,
            corners=np.array(corners, dtype=np.int64).reshape(-1, 2),
            distances=np.concatenate(distances)[index],
            positions=np.stack(positions)[index],
            quaternions=np.stack(quaternions)[index],
            centre=crops.index(strip.centre_crop()),
            windows=len(distinct),
            scale=float(strip.scale),
            input_size=int(strip.input_size),
        )
