"""Relocalizer: backbone + similarity index + crop search, the one pipeline for all methods."""

from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np
import torch

from relocfw.imaging import Strip, to_network_input
from relocfw.interfaces import Backbone, CropSearch, SimilarityIndex
from relocfw.progress import Progress
from relocfw.values import Crop, Localization, Pose


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
    """

    def __init__(
        self,
        backbone: Backbone,
        index: SimilarityIndex,
        crop: CropSearch,
        device: str | torch.device = "cpu",
        batch_size: int = 64,
    ) -> None:
        self.device = torch.device(device)
        self.backbone = backbone.to(self.device).eval()
        self.index = index
        self.crop = crop
        self.batch_size = int(batch_size)

    @torch.inference_mode()
    def _forward(self, inputs: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions, quaternions and descriptors of uint8 inputs, in batches."""
        positions, quaternions, features = [], [], []
        for start in range(0, len(inputs), self.batch_size):
            batch = to_network_input(inputs[start : start + self.batch_size].to(self.device))
            out = self.backbone(batch)
            positions.append(out.positions.double().cpu().numpy())
            quaternions.append(out.quaternions.double().cpu().numpy())
            features.append(out.features.double().cpu().numpy())
        return np.concatenate(positions), np.concatenate(quaternions), np.concatenate(features)

    def describe(self, images: Sequence[np.ndarray], quiet: bool = True) -> np.ndarray:
        """[N, D] descriptors of the centre crops: what the map is built from."""
        size = self.backbone.input_size
        progress = Progress(len(images), "describing map images", quiet=quiet)
        features = []
        for start in range(0, len(images), self.batch_size):
            strips = [Strip(image, size) for image in images[start : start + self.batch_size]]
            batch = torch.stack([s.cut(s.window(s.centre_crop())) for s in strips])
            features.append(self._forward(batch)[2])
            progress.advance(len(strips))
        progress.close()
        return np.concatenate(features)

    def fit(self, images: Sequence[np.ndarray], quiet: bool = True) -> np.ndarray:
        """Build the map from training images; returns their descriptors."""
        features = self.describe(images, quiet=quiet)
        self.index.fit(features)
        return features

    def localize(self, image: np.ndarray) -> Localization:
        """Pose of one RGB image (H x W x 3 uint8) through the crop search."""
        start = time.perf_counter()
        strip = Strip(image, self.backbone.input_size)
        # Network results per strip window: offsets that round to the same window
        # are the same network input, so it is computed once.
        results: dict[tuple[int, int], tuple[float, np.ndarray, np.ndarray]] = {}

        def evaluate(corners: list[tuple[int, int]]) -> None:
            new = list(dict.fromkeys(c for c in corners if c not in results))
            if not new:
                return
            positions, quaternions, features = self._forward(
                torch.stack([strip.cut(c) for c in new])
            )
            distances = self.index.distance(features)
            for i, corner in enumerate(new):
                results[corner] = (float(distances[i]), positions[i], quaternions[i])

        def distance(crops: Sequence[Crop]) -> np.ndarray:
            corners = [strip.window(c) for c in crops]
            evaluate(corners)
            return np.array([results[c][0] for c in corners])

        chosen = self.crop.search(strip.width, strip.height, distance)
        corner = strip.window(chosen)
        evaluate([corner])
        best_distance, position, quaternion = results[corner]
        return Localization(
            pose=Pose(position, quaternion),
            crop=chosen,
            distance=best_distance,
            evaluations=len(results),
            seconds=time.perf_counter() - start,
        )
