"""Scorer: the network and the map as one thing that turns windows into distances.

Every network pass and every map lookup of the pipeline goes through here, so the
pipeline, the crop-premise diagnostic (relocfw.report.window_scores) and the
benchmarks measure the very same path. The two ways to score a candidate window:

- plain: cut the window out of the strip and run the whole network on it (the paper);
- shared: run the trunk once over the whole strip and pool each window's descriptor
  from its maps (relocfw.core.window_pooling);
- scout: cut the window out and run the backbone's cheaper copy on it (an int8 graph,
  `Backbone.scout_features`); its distances only rank candidates.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import numpy as np
import torch
from threadpoolctl import ThreadpoolController

from relocfw.core.imaging import Strip, check_rgb_images, to_network_input
from relocfw.core.interfaces import Backbone, SimilarityIndex
from relocfw.core.network_answers import NetworkAnswers, as_numpy
from relocfw.core.progress import Progress
from relocfw.core.sampling import monte_carlo, sample_share
from relocfw.core.standardise import ZScore, k_nearest
from relocfw.core.window_pooling import StripMaps

Corner = tuple[int, int]  # (y, x) of a window's top-left corner in its strip


class Scorer:
    """Runs the backbone in batches and looks its descriptors up in the map.

    Args:
        backbone: the trained network; put in eval mode (and channels-last when it
            asks for it) on `device`.
        index: the map (fitted by the pipeline's `fit`).
        device: where the network runs.
        batch_size: most windows per forward pass.
    """

    def __init__(
        self,
        backbone: Backbone,
        index: SimilarityIndex,
        device: str | torch.device = "cpu",
        batch_size: int = 16,
    ) -> None:
        self.device = torch.device(device)
        self.backbone = backbone.to(self.device).eval()
        self.memory_format = torch.contiguous_format
        if backbone.channels_last:
            self.memory_format = torch.channels_last
            self.backbone.to(memory_format=self.memory_format)
        self.index = index
        self.batch_size = int(batch_size)
        self._threadpools: ThreadpoolController | None = None  # found on first lookup
        self._cells: int | None = None  # see window_cells
        self._sample_share: float | None = None  # see sampled_passes

    @property
    def crop_scale(self) -> float:
        """The backbone's training crop_scale: the network sees the central
        1/crop_scale of every crop (relocfw.core.imaging.Strip); 1.0 the whole crop."""
        return float(self.backbone.crop_scale)

    def strip(self, image: np.ndarray) -> Strip:
        """The image scaled for this network, ready to cut windows from."""
        return Strip(image, self.backbone.input_size, self.crop_scale)

    @torch.inference_mode()
    def forward(self, inputs: torch.Tensor, samples: int = 0) -> NetworkAnswers:
        """Network answers for uint8 inputs [n, 3, s, s], `batch_size` at a time.

        `samples` Monte Carlo dropout masks per input; 0 (scoring, the map) runs the
        dropout-free network whatever the backbone is configured to sample.
        """
        with monte_carlo(self.backbone, samples):
            parts = [self._forward_batch(batch) for batch in self._batches(inputs)]
        return NetworkAnswers(*(np.concatenate(column) for column in zip(*parts, strict=True)))

    def _batches(self, inputs: torch.Tensor) -> Iterator[torch.Tensor]:
        """uint8 inputs [n, 3, s, s] as the network's inputs on the device, in the
        backbone's memory format, `batch_size` at a time."""
        for start in range(0, len(inputs), self.batch_size):
            batch = to_network_input(inputs[start : start + self.batch_size].to(self.device))
            yield batch.contiguous(memory_format=self.memory_format)

    def _forward_batch(self, batch: torch.Tensor) -> NetworkAnswers:
        out = self.backbone(batch)
        n = len(batch)
        return NetworkAnswers(
            as_numpy(out.positions, n),
            as_numpy(out.quaternions, n),
            as_numpy(out.features, n),
            as_numpy(out.position_spread, n),
            as_numpy(out.orientation_spread_deg, n),
        )

    def describe(self, images: Sequence[np.ndarray], quiet: bool = True) -> np.ndarray:
        """[N, D] dropout-free descriptors of the images' centre crops (the map's)."""
        check_rgb_images(images)
        progress = Progress(len(images), "describing map images", quiet=quiet)
        features = []
        for start in range(0, len(images), self.batch_size):
            strips = [self.strip(image) for image in images[start : start + self.batch_size]]
            batch = torch.stack([s.cut(s.window(s.centre_crop())) for s in strips])
            features.append(self.forward(batch).features)
            progress.advance(len(strips))
        progress.close()
        return np.concatenate(features)

    def map_distance(self, features: np.ndarray) -> np.ndarray:
        """[n] map distances of [n, D] descriptors, on one BLAS thread.

        A query's index lookups are small. A multi-threaded BLAS call leaves its
        workers spinning afterwards, competing with the network's threads for the
        same cores: on 2 cores it nearly doubled the sweep's time per query.
        """
        with self.one_blas_thread():
            return self.index.distance(features)

    def distance_scale(self, features: np.ndarray) -> float:
        """A unit for map distances that is comparable across models: the map images'
        own median map distance. An index that holds the images themselves (exhaustive)
        gives them 0; then the median distance from each map image to its nearest other
        one (standardised, as the indexes measure), and 1 if even that is 0."""
        own = float(np.median(self.map_distance(features)))
        if own > 0:
            return own
        points = ZScore().fit(features)(features)
        others = k_nearest(points, points, 2)[0][:, -1]
        spacing = float(np.median(others))
        return spacing if spacing > 0 else 1.0

    def one_blas_thread(self):  # noqa: ANN201 - threadpoolctl's context manager
        if self._threadpools is None:
            self._threadpools = ThreadpoolController()
        return self._threadpools.limit(limits=1, user_api="blas")

    def plain(self, strip: Strip, corners: Sequence[Corner]) -> tuple[np.ndarray, NetworkAnswers]:
        """Map distances [n] and network answers of n strip windows (scoring=plain)."""
        return self.plain_of_windows(torch.stack([strip.cut(c) for c in corners]))

    def plain_together(
        self, requests: Sequence[tuple[Strip, Sequence[Corner]]]
    ) -> list[tuple[np.ndarray, NetworkAnswers]]:
        """`plain` for several queries' windows in merged forward passes, split back.

        A window's answer does not depend on its batch-mates, so each query gets what
        `plain` would give it alone.
        """
        distances, answers = self.plain_of_windows(merged_windows(requests))
        return [
            (distances[rows], NetworkAnswers(*(column[rows] for column in answers)))
            for rows in request_rows(requests)
        ]

    @torch.inference_mode()
    def scout_together(
        self, requests: Sequence[tuple[Strip, Sequence[Corner]]]
    ) -> list[np.ndarray]:
        """Map distances of several queries' windows by the backbone's scout
        (scoring=scout), `batch_size` windows per pass, split back per query."""
        # Dropout-free, as every scoring pass (a backbone may sample by default).
        with monte_carlo(self.backbone, 0):
            features = [
                as_numpy(self.backbone.scout_features(batch), len(batch))
                for batch in self._batches(merged_windows(requests))
            ]
        distances = self.map_distance(np.concatenate(features))
        return [distances[rows] for rows in request_rows(requests)]

    def plain_of_windows(self, windows: torch.Tensor) -> tuple[np.ndarray, NetworkAnswers]:
        """Map distances [n] and network answers of n uint8 windows [n, 3, s, s]."""
        answers = self.forward(windows)
        return self.map_distance(answers.features), answers

    @torch.inference_mode()
    def strip_maps(self, strip: Strip) -> StripMaps:
        """The trunk's maps of the whole strip: one pass for every candidate window."""
        pixels = to_network_input(strip.pixels[None].to(self.device))
        pixels = pixels.contiguous(memory_format=self.memory_format)
        maps = self.backbone.feature_maps(pixels)[0]
        height, width = strip.pixels.shape[1:]
        return StripMaps(maps, height, width, self.backbone.input_size, self.window_cells())

    @torch.inference_mode()
    def shared(self, maps: StripMaps, corners: Sequence[Corner]) -> np.ndarray:
        """Map distances [n] of windows pooled from a strip's maps (scoring=shared)."""
        features = self.backbone.describe_pooled(maps.pooled(list(corners)))
        return self.map_distance(features.double().cpu().numpy())

    @torch.inference_mode()
    def window_cells(self) -> int | None:
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

    def strip_passes(self, strip: Strip) -> float:
        """A pass over the whole strip in window passes: its area over a window's (the
        trunk dominates the network's work)."""
        side = self.backbone.input_size
        return strip.pixels.shape[1] * strip.pixels.shape[2] / side**2

    def sampled_passes(self, windows: int, masks: int) -> float:
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


def merged_windows(requests: Sequence[tuple[Strip, Sequence[Corner]]]) -> torch.Tensor:
    """uint8 [n, 3, s, s]: every request's windows, the requests in order."""
    return torch.stack([strip.cut(c) for strip, corners in requests for c in corners])


def request_rows(requests: Sequence[tuple[Strip, Sequence[Corner]]]) -> list[slice]:
    """Each request's rows in `merged_windows(requests)`."""
    ends = np.cumsum([len(corners) for _, corners in requests]).tolist()
    return [slice(start, end) for start, end in zip([0, *ends[:-1]], ends, strict=True)]
