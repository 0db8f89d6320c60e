"""The cameras of a COLMAP sparse model: read, checked, and matched to its images.

relocfw's poses need no intrinsics, but a camera file that names an unknown model or
holds impossible values means a damaged model, and the structure-based stage will
project points with these cameras: so they are read and checked with the images, and
kept (ColmapDataset.cameras, ColmapDataset.camera(name)).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

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
