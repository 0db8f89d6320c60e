"""Every crop offset of one query with its map distance and pose, for the diagnostic.

For studying the paper's premise (relocfw.report.diagnosis): the offsets are those
crop=sweep tries at stride 1, cut as the pipeline cuts them (crop_scale included),
scored by the plain network whatever the options' scoring says, through the
pipeline's own Scorer, and each pose is the network's pose of that crop (a refiner,
e.g. refine=retrieval, is not applied). So the diagnostic measures what a search sees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from relocfw.core.imaging import check_rgb_image
from relocfw.core.interfaces import crop_at, crop_side_and_span
from relocfw.core.pipeline import Relocalizer
from relocfw.core.values import Crop


@dataclass(frozen=True)
class WindowScores:
    """Every crop offset of one query: its window, map distance and pose.

    Entry i is offset i along the long axis (crop=sweep at stride 1 tries exactly
    these), so a study of the crop premise sees the very windows, distances and poses
    the pipeline would produce.
    """

    crops: tuple[Crop, ...]  # [n] in original image pixels, as Localization.crop
    corners: np.ndarray  # [n, 2] int (y, x) of each offset's window in the strip
    distances: np.ndarray  # [n] map distance of each window's descriptor
    positions: np.ndarray  # [n, 3] the pose answered were that crop chosen
    quaternions: np.ndarray  # [n, 4]
    features: np.ndarray  # [n, D] each window's descriptor (before the map's standardising)
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


@torch.inference_mode()
def score_windows(relocalizer: Relocalizer, image: np.ndarray) -> WindowScores:
    """Every crop offset of one RGB image with its map distance and pose.

    Offsets that round to the same window share one network pass; windows go through
    the network `batch_size` at a time, so memory stays flat however long the image.

    Raises:
        DataError: the image is not H x W x 3 uint8 RGB.
    """
    check_rgb_image(image)
    scorer = relocalizer.scorer
    strip = scorer.strip(image)
    _, span = crop_side_and_span(strip.width, strip.height)
    crops = tuple(crop_at(offset, strip.width, strip.height) for offset in range(span + 1))
    corners = [strip.window(c) for c in crops]
    distinct = list(dict.fromkeys(corners))
    distances, positions, quaternions, features = [], [], [], []
    for start in range(0, len(distinct), scorer.batch_size):
        chunk_distances, answers = scorer.plain(strip, distinct[start : start + scorer.batch_size])
        poses = [relocalizer.pose_of(answers.row(i)) for i in range(len(chunk_distances))]
        distances.append(np.asarray(chunk_distances, dtype=np.float64))
        features.append(np.asarray(answers.features, dtype=np.float64))
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
        features=np.concatenate(features)[index],
        centre=crops.index(strip.centre_crop()),
        windows=len(distinct),
        scale=float(strip.scale),
        input_size=int(strip.input_size),
    )
