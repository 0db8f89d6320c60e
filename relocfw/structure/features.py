"""Local features of an image: SIFT keypoints with RootSIFT descriptors.

RootSIFT (Arandjelovic and Zisserman, "Three things everyone should know to improve
object retrieval", CVPR 2012): each SIFT descriptor is L1-normalised and square-rooted
element-wise. The result has unit L2 norm, and the Euclidean distance between two
RootSIFT descriptors is a monotone function of the Hellinger kernel of the SIFT ones
(||a' - b'||^2 = 2 - 2 sum sqrt(a_i b_i) for L1-normalised a, b), which compares
histograms better than the Euclidean distance of SIFT itself, at no cost at matching.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.imaging import check_rgb_image
from relocfw.core.options import integer_at_least

SIFT_DIMENSIONS = 128
# The most keypoints any image is asked for, far above any use: a size from a model
# file or the command line above it would reach OpenCV (SIFT_create raises for 2**40
# at every image) or hold more features than an image of the largest camera has.
MOST_FEATURES = 100_000


@dataclass(frozen=True)
class LocalFeatures:
    """Keypoints of one image and their descriptors, row i describing keypoint i.

    Attributes:
        keypoints: [N, 2] float32 pixel (x, y), measured from the centre of the
            top-left pixel (OpenCV's convention, as relocfw.core.camera).
        descriptors: [N, D] float32 (D = 128 for RootSIFT), one row per keypoint.

    Both are copied, made read-only and checked when the value is made.

    Raises:
        DataError: when either is not a 2-D array of finite numbers, keypoints do not
            have 2 columns, or the two do not have the same number of rows.
    """

    keypoints: np.ndarray
    descriptors: np.ndarray

    def __post_init__(self) -> None:
        # Copies, so a caller's later edits cannot change a frozen value.
        try:
            keypoints = np.array(self.keypoints, dtype=np.float32)
        except (TypeError, ValueError):
            raise DataError("keypoints must be an [N, 2] array of numbers") from None
        try:
            descriptors = np.array(self.descriptors, dtype=np.float32)
        except (TypeError, ValueError):
            raise DataError("descriptors must be an [N, D] array of numbers") from None
        if keypoints.ndim != 2 or keypoints.shape[1] != 2:
            raise DataError(f"keypoints must be an [N, 2] array, got shape {keypoints.shape}")
        if descriptors.ndim != 2:
            raise DataError(f"descriptors must be an [N, D] array, got shape {descriptors.shape}")
        if len(keypoints) != len(descriptors):
            raise DataError(
                f"{len(keypoints)} keypoints but {len(descriptors)} descriptors; "
                "each keypoint needs exactly one descriptor row"
            )
        if not (np.isfinite(keypoints).all() and np.isfinite(descriptors).all()):
            raise DataError("keypoints and descriptors must be finite (found NaN or infinity)")
        keypoints.setflags(write=False)
        descriptors.setflags(write=False)
        object.__setattr__(self, "keypoints", keypoints)
        object.__setattr__(self, "descriptors", descriptors)

    def __len__(self) -> int:
        return len(self.keypoints)


def root_sift(descriptors: np.ndarray) -> np.ndarray:
    """RootSIFT of SIFT descriptors: L1-normalise each row, then square-root it.

    Args:
        descriptors: [N, D] non-negative SIFT descriptors.

    Returns:
        [N, D] float32 rows of unit L2 norm (a row of zeros stays zero).
    """
    values = np.asarray(descriptors, dtype=np.float32)
    l1 = np.abs(values).sum(axis=1, keepdims=True)
    # SIFT rows are non-negative histograms; the floor only guards an all-zero row.
    return np.sqrt(np.abs(values) / np.maximum(l1, np.finfo(np.float32).tiny))


def extract_rootsift(
    image: np.ndarray, max_features: int = 1024, image_scale: float = 1.0
) -> LocalFeatures:
    """SIFT keypoints of an RGB image with RootSIFT descriptors (OpenCV's SIFT).

    Args:
        image: [H, W, 3] uint8 RGB (relocfw.core.imaging.read_rgb reads one).
        max_features: the most keypoints to keep (>= 1), the strongest by response.
        image_scale: the size, as a share of the image's, that SIFT runs on, in
            (0, 1]: 0.5 halves each side (area-averaged), about 4x less work, and drops
            the finest keypoints. Keypoints are returned in the pixels of `image`
            either way, so a camera of the full image still describes them.

    Returns:
        LocalFeatures with at most `max_features` rows: keypoints [N, 2] float32 pixel
        (x, y), descriptors [N, 128] float32 of unit L2 norm, strongest first. An image
        without texture gives N = 0.

    Raises:
        DataError: when `image` is not an [H, W, 3] uint8 array.
        ConfigError: when `max_features` is not an integer in 1 .. MOST_FEATURES
            (OpenCV reads 0 as "no limit", which would silently lift the bound).
    """
    check_rgb_image(image)
    max_features = integer_at_least("max_features", max_features, 1)
    if max_features > MOST_FEATURES:
        raise ConfigError(f"max_features must be at most {MOST_FEATURES}, got {max_features}")
    scale = checked_image_scale(image_scale)
    grey = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    if scale != 1.0:
        height, width = grey.shape
        size = (max(1, round(width * scale)), max(1, round(height * scale)))
        grey = cv2.resize(grey, size, interpolation=cv2.INTER_AREA)
    sift = cv2.SIFT_create(nfeatures=max_features)
    keypoints, descriptors = sift.detectAndCompute(grey, None)
    if descriptors is None or len(keypoints) == 0:
        return LocalFeatures(np.zeros((0, 2)), np.zeros((0, SIFT_DIMENSIONS)))
    # OpenCV's cut keeps every keypoint tied with the last one's response, and a
    # point with two dominant orientations becomes two keypoints, so it can return
    # more than nfeatures: sort by response (stable, so equal ones keep OpenCV's
    # order) and cut again to keep the promise.
    responses = np.array([k.response for k in keypoints], dtype=np.float32)
    order = np.argsort(-responses, kind="stable")[:max_features]
    points = np.array([keypoints[i].pt for i in order], dtype=np.float32).reshape(-1, 2)
    if scale != 1.0:
        points = to_full_image(
            points, image.shape[1] / grey.shape[1], image.shape[0] / grey.shape[0]
        )
    return LocalFeatures(points, root_sift(descriptors[order]))


def checked_image_scale(image_scale: object) -> float:
    """`image_scale` as a float in (0, 1], or a ConfigError naming it (above 1 would
    upsample: slower, and no keypoint the image does not hold)."""
    try:
        value = float(image_scale)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        value = float("nan")
    if isinstance(image_scale, bool) or not 0.0 < value <= 1.0:
        raise ConfigError(f"image_scale must be in (0, 1] (1: full size), got {image_scale!r}")
    return value


def to_full_image(points: np.ndarray, scale_x: float, scale_y: float) -> np.ndarray:
    """Pixels of a resized image in the pixels of the image it was resized from.

    Pixel centres sit at integers (OpenCV's convention): the resized image's pixel
    edge -0.5 is the full image's edge -0.5, hence the half-pixel shifts.
    """
    full = np.empty_like(points)
    full[:, 0] = (points[:, 0] + 0.5) * scale_x - 0.5
    full[:, 1] = (points[:, 1] + 0.5) * scale_y - 0.5
    return full
