"""The cameras of a COLMAP sparse model: read, checked, and matched to its images.

relocfw's poses need no intrinsics, but a camera file that names an unknown model or
holds impossible values means a damaged model, and the structure-based stage will
project points with these cameras: so they are read and checked with the images, and
kept (ColmapDataset.cameras, ColmapDataset.camera(name)). A camera without lens
distortion also becomes relocfw's PinholeCamera (pinhole_of), each frame's
`Frame.camera`; for any other, why_not_pinhole says why in one line.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import DataError
from relocfw.data.colmap_format import (
    ColmapCamera,
    ColmapImage,
    read_cameras_binary,
    read_cameras_text,
)
from relocfw.data.on_error import OnError


def model_cameras_file(images_file: Path) -> Path:
    """The cameras file of the same format beside an images file, as COLMAP writes a model.

    Raises:
        DataError: there is none (images.* alone is not a whole sparse model).
    """
    images_file = Path(images_file)
    path = images_file.with_name(f"cameras{images_file.suffix}")
    if not path.is_file():
        raise DataError(
            f"{images_file.parent}: no {path.name} beside {images_file.name} (a COLMAP "
            "sparse model has both; the images' cameras are read from it)"
        )
    return path


def read_model_cameras(path: Path, on_error: OnError | None = None) -> dict[int, ColmapCamera]:
    """Cameras of a cameras.bin or cameras.txt by CAMERA_ID; duplicate ids are refused."""
    path = Path(path)
    on_error = on_error or OnError()
    binary = path.suffix == ".bin"
    cameras = read_cameras_binary(path, on_error) if binary else read_cameras_text(path, on_error)
    by_id: dict[int, ColmapCamera] = {}
    for camera in cameras:
        if camera.camera_id in by_id:
            on_error.handle(
                DataError(
                    f"{camera.source}: duplicate CAMERA_ID {camera.camera_id} "
                    f"(first at {by_id[camera.camera_id].source})"
                )
            )
            continue
        by_id[camera.camera_id] = camera
    return by_id


def images_with_cameras(
    images: Sequence[ColmapImage],
    cameras: dict[int, ColmapCamera],
    cameras_file: Path,
    on_error: OnError,
) -> list[ColmapImage]:
    """The images whose CAMERA_ID is a camera of the model; the others go to `on_error`."""
    kept = []
    for image in images:
        if image.camera_id in cameras:
            kept.append(image)
            continue
        on_error.handle(
            DataError(
                f"{image.source}: image {image.name!r} has CAMERA_ID {image.camera_id}, "
                f"which {cameras_file} does not hold"
            )
        )
    if not kept:
        raise DataError(f"{cameras_file}: no registered image has its camera here")
    return kept


# Models that are a pinhole when their distortion parameters (those after the focal
# lengths and principal point) are all 0: PINHOLE and SIMPLE_PINHOLE have none. The
# fisheye and FOV models are not, even with zero coefficients (their projection is
# not x / z), so they never give a pinhole camera.
PINHOLE_WITH_ZERO_DISTORTION = {
    "SIMPLE_PINHOLE": 3,
    "PINHOLE": 4,
    "SIMPLE_RADIAL": 3,
    "RADIAL": 3,
    "OPENCV": 4,
    "FULL_OPENCV": 4,
}


def pinhole_of(camera: ColmapCamera) -> PinholeCamera | None:
    """relocfw's pinhole camera of a COLMAP camera without lens distortion, else None.

    PINHOLE (fx fy cx cy) and SIMPLE_PINHOLE (f cx cy) give one; so do SIMPLE_RADIAL,
    RADIAL, OPENCV and FULL_OPENCV whose distortion parameters are exactly 0 (a model
    undistorted beforehand, or calibrated with distortion fixed). Any other camera
    needs its images undistorted (`colmap image_undistorter` writes a PINHOLE model)
    before points can be projected with a pinhole: `why_not_pinhole` says why in one
    line.

    COLMAP measures pixel coordinates from the image's top-left corner (the top-left
    pixel's centre is (0.5, 0.5)); relocfw from that pixel's centre, so the principal
    point moves by half a pixel: cx = cx_colmap - 0.5, cy = cy_colmap - 0.5.

    Returns:
        PinholeCamera(fx, fy, cx, cy, WIDTH, HEIGHT), or None.
    """
    count = PINHOLE_WITH_ZERO_DISTORTION.get(camera.model)
    if count is None or any(value != 0 for value in camera.params[count:]):
        return None
    if count == 3:  # one focal length: f cx cy
        focal, cx, cy = camera.params[:3]
        fx = fy = focal
    else:
        fx, fy, cx, cy = camera.params[:4]
    return PinholeCamera(fx, fy, cx - 0.5, cy - 0.5, camera.width, camera.height)


def why_not_pinhole(camera: ColmapCamera) -> str:
    """Why `pinhole_of(camera)` is None, in one line; "" when it is not None.

    For a later stage's message, e.g. "structure-based refinement needs undistorted
    images: camera 3 is OPENCV with lens distortion (k1 k2 p1 p2 = ...)".
    """
    if pinhole_of(camera) is not None:
        return ""
    count = PINHOLE_WITH_ZERO_DISTORTION.get(camera.model)
    if count is None:
        return f"camera {camera.camera_id} is {camera.model}, not a pinhole projection"
    distortion = " ".join(f"{value:g}" for value in camera.params[count:])
    return f"camera {camera.camera_id} is {camera.model} with lens distortion ({distortion})"
