"""COLMAP sparse models on disk: cameras and images, text and binary, read and written.

The values are kept exactly as COLMAP stores them: per image the world-to-camera
rotation as a unit quaternion (QW, QX, QY, QZ) and the translation (TX, TY, TZ), so
that a point maps as x_camera = R x_world + t. Turning them into relocfw's
camera-to-world poses is `relocfw.data.colmap`'s job.

Layouts (COLMAP's "Output Format" documentation; binary is little endian):
    cameras.txt   CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]             one line per camera
    images.txt    IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME      then a POINTS2D line
                  (X Y POINT3D_ID triples; empty when the image has none)
    cameras.bin   uint64 count; per camera uint32 id, int32 model id, uint64 width,
                  uint64 height, float64 params[n(model)]
    images.bin    uint64 count; per image uint32 id, float64 qvec[4], float64 tvec[3],
                  uint32 camera id, NAME + NUL, uint64 n, n x (float64 x, float64 y,
                  uint64 point3D id)
The 2-D observations and points3D are passed over here: relocalization needs only
where each image was taken (relocfw.data.colmap_points reads them for the
structure-based stage). Cameras are read and checked (a known model, its parameter
count, a positive size and focal length) and kept for the structure-based stage.
Newer COLMAP versions also write rigs and frames files; they still write each
registered image's own world-to-camera pose in images.*, so those are not needed
either (checked with files written by pycolmap 4.2.1).
"""

from __future__ import annotations

import math
import mmap
import struct
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from relocfw.core.errors import DataError
from relocfw.data.on_error import OnError

# Model id -> (name, number of parameters), checked against pycolmap 4.2.1 and
# COLMAP's src/colmap/sensor/models.h. Both formats are held to it: cameras.bin stores
# only the id (an unknown one cannot be read past), and a cameras.txt model name
# outside it, or a parameter count that differs, is a damaged or mistyped file.
CAMERA_MODELS: dict[int, tuple[str, int]] = {
    0: ("SIMPLE_PINHOLE", 3),
    1: ("PINHOLE", 4),
    2: ("SIMPLE_RADIAL", 4),
    3: ("RADIAL", 5),
    4: ("OPENCV", 8),
    5: ("OPENCV_FISHEYE", 8),
    6: ("FULL_OPENCV", 12),
    7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4),
    9: ("RADIAL_FISHEYE", 5),
    10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
    12: ("SIMPLE_DIVISION", 4),
    13: ("DIVISION", 5),
    14: ("SIMPLE_FISHEYE", 3),
    15: ("FISHEYE", 4),
    16: ("EUCM", 6),
    17: ("EQUIRECTANGULAR", 2),
}
MODEL_IDS = {name: (model_id, count) for model_id, (name, count) in CAMERA_MODELS.items()}
# How many leading parameters must be positive: the focal lengths (f, or fx fy, as
# COLMAP's focal_length_idxs), and for EQUIRECTANGULAR, which has none, the image
# size (w h) that its two parameters are.
SIMPLE_MODELS = {
    "SIMPLE_PINHOLE",
    "SIMPLE_RADIAL",
    "RADIAL",
    "SIMPLE_RADIAL_FISHEYE",
    "RADIAL_FISHEYE",
    "SIMPLE_DIVISION",
    "SIMPLE_FISHEYE",
}
POSITIVE_PARAMS = {name: 1 if name in SIMPLE_MODELS else 2 for name in MODEL_IDS}

IMAGE_HEAD = struct.Struct("<I4d3dI")  # image id, qvec, tvec, camera id
CAMERA_HEAD = struct.Struct("<IiQQ")  # camera id, model id, width, height
COUNT = struct.Struct("<Q")
POINT2D_BYTES = 24  # float64 x, float64 y, uint64 point3D id


@dataclass(frozen=True)
class ColmapCamera:
    """One camera of cameras.txt / cameras.bin: COLMAP's intrinsics, as stored.

    Not needed for poses; kept (ColmapDataset.camera) for a structure-based stage.

    Attributes:
        model: a name of CAMERA_MODELS, e.g. "PINHOLE".
        width, height: the image size in pixels.
        params: the model's parameters in COLMAP's order (PINHOLE: fx fy cx cy).
        source: where it was read, for error messages (not compared).
    """

    camera_id: int
    model: str
    width: int
    height: int
    params: tuple[float, ...]
    source: str = field(default="", compare=False)


def check_camera(camera: ColmapCamera) -> ColmapCamera:
    """`camera`, if it is one COLMAP could have written, else a DataError naming its source.

    Known model, the model's parameter count, a positive width and height, and
    positive focal lengths: what a later stage projecting points relies on.
    """
    where = camera.source or f"CAMERA_ID {camera.camera_id}"
    if camera.model not in MODEL_IDS:
        raise DataError(
            f"{where}: unknown COLMAP camera model {camera.model!r} (known: {', '.join(MODEL_IDS)})"
        )
    _, count = MODEL_IDS[camera.model]
    if len(camera.params) != count:
        raise DataError(
            f"{where}: camera model {camera.model} takes {count} parameters, "
            f"got {len(camera.params)}"
        )
    if camera.width <= 0 or camera.height <= 0:
        raise DataError(
            f"{where}: camera size must be positive, got WIDTH {camera.width} "
            f"HEIGHT {camera.height}"
        )
    positive = camera.params[: POSITIVE_PARAMS[camera.model]]
    if not all(value > 0 for value in positive):
        what = "image size" if camera.model == "EQUIRECTANGULAR" else "focal length"
        raise DataError(
            f"{where}: the {what} of a {camera.model} camera must be positive, got {list(positive)}"
        )
    return camera


@dataclass(frozen=True)
class ColmapImage:
    """One registered image of images.txt / images.bin, in COLMAP's own convention.

    Attributes:
        qvec: world-to-camera rotation (w, x, y, z), as stored.
        tvec: world-to-camera translation, as stored: x_camera = R x_world + t.
        source: where it was read, for error messages ("images.txt:12" or
            "images.bin: image 3 of 10").
    """

    image_id: int
    qvec: tuple[float, float, float, float]
    tvec: tuple[float, float, float]
    camera_id: int
    name: str
    source: str = ""


# ---------------------------------------------------------------------------- text


def _text_lines(path: Path) -> list[str]:
    path = Path(path)
    if not path.is_file():
        raise DataError(f"file not found: {path}")
    try:
        return path.read_text(encoding="utf-8").splitlines()
    except UnicodeDecodeError as error:
        raise DataError(f"{path}: not a text file ({error})") from error


def _integer(text: str, source: str, what: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise DataError(f"{source}: {what} must be an integer, got {text!r}") from None


def _floats(fields: Sequence[str], source: str, what: str) -> tuple[float, ...]:
    """Finite floats, or a DataError naming the line (COLMAP never writes NaN here)."""
    try:
        values = tuple(float(v) for v in fields)
    except ValueError as error:
        raise DataError(f"{source}: {what}: not a number ({error})") from None
    if not all(math.isfinite(v) for v in values):
        raise DataError(f"{source}: {what}: NaN or infinite value in {list(fields)}")
    return values


def _is_points_line(line: str) -> bool:
    """Whether a line can be an image's POINTS2D line: empty, or X Y POINT3D_ID triples.

    Only the count and the last field are looked at (a large model has millions of
    numbers here); an image line ends in its NAME, which is not an integer, so a
    missing POINTS2D line is caught instead of swallowing the next image.
    """
    fields = line.split()
    if not fields:
        return True
    if len(fields) % 3:
        return False
    try:
        int(fields[-1])
    except ValueError:
        return False
    return True


def read_images_text(path: Path, on_error: OnError | None = None) -> list[ColmapImage]:
    """The images of an images.txt, in file order.

    A bad image line goes to `on_error` (fail: raise; skip: leave it out). A missing
    POINTS2D line breaks the two-lines-per-image structure and always raises.
    """
    on_error = on_error or OnError()
    path = Path(path)
    lines = _text_lines(path)
    images: list[ColmapImage] = []
    number = 0
    while number < len(lines):
        line = lines[number].strip()
        number += 1
        if not line or line.startswith("#"):
            continue
        source = f"{path}:{number}"
        # As COLMAP reads it: the line right after an image line is its POINTS2D line.
        if number < len(lines) and not _is_points_line(lines[number]):
            raise DataError(
                f"{path}:{number + 1}: expected the POINTS2D line of the image on line "
                f"{number} (X Y POINT3D_ID triples, or an empty line), found "
                f"{lines[number].strip()[:80]!r}"
            )
        number += 1
        try:
            images.append(_image_from_line(line, source))
        except DataError as error:
            on_error.handle(error)
    return images


def _image_from_line(line: str, source: str) -> ColmapImage:
    fields = line.split(None, 9)
    if len(fields) != 10:
        raise DataError(
            f"{source}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', "
            f"found {len(fields)} values"
        )
    values = _floats(fields[1:8], source, "QW QX QY QZ TX TY TZ")
    return ColmapImage(
        image_id=_integer(fields[0], source, "IMAGE_ID"),
        qvec=values[:4],  # type: ignore[arg-type]
        tvec=values[4:],  # type: ignore[arg-type]
        camera_id=_integer(fields[8], source, "CAMERA_ID"),
        name=fields[9].strip(),
        source=source,
    )


def read_cameras_text(path: Path, on_error: OnError | None = None) -> list[ColmapCamera]:
    """The cameras of a cameras.txt, in file order, each checked (check_camera).

    A bad camera line goes to `on_error` (fail: raise; skip: leave it out, and the
    images taken with it are then left out for want of their camera).
    """
    on_error = on_error or OnError()
    path = Path(path)
    cameras = []
    for number, raw in enumerate(_text_lines(path), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        try:
            cameras.append(check_camera(_camera_from_line(line, f"{path}:{number}")))
        except DataError as error:
            on_error.handle(error)
    return cameras


def _camera_from_line(line: str, source: str) -> ColmapCamera:
    fields = line.split()
    if len(fields) < 4:
        raise DataError(f"{source}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]'")
    return ColmapCamera(
        camera_id=_integer(fields[0], source, "CAMERA_ID"),
        model=fields[1],
        width=_integer(fields[2], source, "WIDTH"),
        height=_integer(fields[3], source, "HEIGHT"),
        params=_floats(fields[4:], source, "PARAMS"),
        source=source,
    )


def _number_text(value: float) -> str:
    # repr is the shortest text that reads back to the same float: lossless round trips
    # (+ 0.0 writes -0.0 as 0.0).
    return repr(float(value) + 0.0)


def write_images_text(path: Path, images: Sequence[ColmapImage]) -> None:
    """images.txt as COLMAP writes it, each image with an empty POINTS2D line."""
    lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
        f"# Number of images: {len(images)}, mean observations per image: 0",
    ]
    for image in images:
        _check_name(image.name)
        numbers = " ".join(_number_text(v) for v in (*image.qvec, *image.tvec))
        lines += [f"{image.image_id} {numbers} {image.camera_id} {image.name}", ""]
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


def write_cameras_text(path: Path, cameras: Sequence[ColmapCamera]) -> None:
    """cameras.txt as COLMAP writes it."""
    lines = [
        "# Camera list with one line of data per camera:",
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
        f"# Number of cameras: {len(cameras)}",
    ]
    for camera in cameras:
        params = " ".join(_number_text(v) for v in camera.params)
        lines.append(
            f"{camera.camera_id} {camera.model} {camera.width} {camera.height} {params}".rstrip()
        )
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


def _check_name(name: str) -> None:
    # COLMAP's readers split the text line at spaces and the binary name at NUL.
    if not name or any(c in name for c in " \t\n\r\0"):
        raise ValueError(f"COLMAP image names cannot be empty or hold whitespace: {name!r}")


# -------------------------------------------------------------------------- binary


class _BinaryFile:
    """Bounds-checked little-endian reads from a memory-mapped file.

    Every read names the file, the byte offset and what was being read, so a
    truncated or corrupt file gives an actionable message instead of a struct.error.
    """

    def __init__(self, data: mmap.mmap | bytes, path: Path) -> None:
        self.data = data
        self.path = path
        self.offset = 0

    def unpack(self, layout: struct.Struct, what: str) -> tuple:
        end = self.offset + layout.size
        if end > len(self.data):
            raise DataError(
                f"{self.path}: truncated or corrupt at byte {self.offset} of "
                f"{len(self.data)} (reading {what})"
            )
        values = layout.unpack_from(self.data, self.offset)
        self.offset = end
        return values

    def skip(self, count: int, what: str) -> None:
        if count > len(self.data) - self.offset:
            raise DataError(
                f"{self.path}: truncated or corrupt at byte {self.offset} of "
                f"{len(self.data)} ({what}: {count} bytes announced, "
                f"{len(self.data) - self.offset} left)"
            )
        self.offset += count

    def name(self, what: str) -> str:
        end = self.data.find(b"\0", self.offset)
        if end < 0:
            raise DataError(
                f"{self.path}: truncated or corrupt at byte {self.offset} ({what} has no NUL end)"
            )
        raw = bytes(self.data[self.offset : end])
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError as error:
            raise DataError(
                f"{self.path}: corrupt at byte {self.offset} ({what} is not UTF-8: {error})"
            ) from None
        self.offset = end + 1
        return text

    def count(self, minimum_record: int, what: str) -> int:
        """The leading uint64 record count, refused when the file cannot hold that many."""
        (count,) = self.unpack(COUNT, f"the number of {what}")
        if count * minimum_record > len(self.data) - self.offset:
            raise DataError(
                f"{self.path}: corrupt header: {count} {what} announced, but "
                f"{len(self.data) - self.offset} bytes cannot hold them"
            )
        return count

    def finish(self, what: str) -> None:
        if self.offset != len(self.data):
            raise DataError(
                f"{self.path}: corrupt: {len(self.data) - self.offset} bytes left after the "
                f"last of the {what} (at byte {self.offset})"
            )


@contextmanager
def _mapped(path: Path) -> Iterator[_BinaryFile]:
    path = Path(path)
    if not path.is_file():
        raise DataError(f"file not found: {path}")
    with open(path, "rb") as stream:
        if path.stat().st_size == 0:
            yield _BinaryFile(b"", path)
            return
        # A memory map reads the names and headers in place and skips the 2-D points
        # (most of a large images.bin) without loading them.
        with mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_READ) as data:
            yield _BinaryFile(data, path)


def read_images_binary(path: Path) -> list[ColmapImage]:
    """The images of an images.bin, in file order.

    A truncated or otherwise corrupt file always raises: nothing after the damage can
    be found again, so there is no entry to skip.
    """
    images: list[ColmapImage] = []
    with _mapped(path) as reader:
        count = reader.count(IMAGE_HEAD.size + 1 + COUNT.size, "images")
        for index in range(count):
            what = f"image {index + 1} of {count}"
            image_id, qw, qx, qy, qz, tx, ty, tz, camera_id = reader.unpack(IMAGE_HEAD, what)
            name = reader.name(f"the name of {what}")
            (points,) = reader.unpack(COUNT, f"the point count of {what}")
            reader.skip(points * POINT2D_BYTES, f"the 2-D points of {what}")
            images.append(
                ColmapImage(
                    image_id=image_id,
                    qvec=(qw, qx, qy, qz),
                    tvec=(tx, ty, tz),
                    camera_id=camera_id,
                    name=name,
                    source=f"{reader.path}: {what} (IMAGE_ID {image_id})",
                )
            )
        reader.finish("images")
    return images


def read_cameras_binary(path: Path, on_error: OnError | None = None) -> list[ColmapCamera]:
    """The cameras of a cameras.bin, in file order, each checked (check_camera).

    A model id not in CAMERA_MODELS (its parameter count is unknown) or a truncated
    file always raises: nothing after the damage can be found again. A camera with
    impossible values goes to `on_error`, as in read_cameras_text.
    """
    on_error = on_error or OnError()
    cameras = []
    with _mapped(path) as reader:
        count = reader.count(CAMERA_HEAD.size, "cameras")
        for index in range(count):
            what = f"camera {index + 1} of {count}"
            camera_id, model_id, width, height = reader.unpack(CAMERA_HEAD, what)
            if model_id not in CAMERA_MODELS:
                raise DataError(
                    f"{reader.path}: {what} (CAMERA_ID {camera_id}) has camera model id "
                    f"{model_id}, which relocfw does not know (known: 0-{max(CAMERA_MODELS)}); "
                    "its parameter count is unknown, so the file cannot be read past it"
                )
            model, params = CAMERA_MODELS[model_id]
            values = reader.unpack(struct.Struct(f"<{params}d"), f"the parameters of {what}")
            source = f"{reader.path}: {what} (CAMERA_ID {camera_id})"
            camera = ColmapCamera(camera_id, model, width, height, tuple(values), source)
            try:
                if not all(math.isfinite(v) for v in values):
                    raise DataError(f"{source}: NaN or infinite value in PARAMS {list(values)}")
                cameras.append(check_camera(camera))
            except DataError as error:
                on_error.handle(error)
        reader.finish("cameras")
    return cameras


def write_images_binary(path: Path, images: Sequence[ColmapImage]) -> None:
    """images.bin as COLMAP writes it, each image with no 2-D points."""
    parts = [COUNT.pack(len(images))]
    for image in images:
        _check_name(image.name)
        parts += [
            IMAGE_HEAD.pack(image.image_id, *image.qvec, *image.tvec, image.camera_id),
            image.name.encode("utf-8") + b"\0",
            COUNT.pack(0),
        ]
    Path(path).write_bytes(b"".join(parts))


def write_cameras_binary(path: Path, cameras: Sequence[ColmapCamera]) -> None:
    """cameras.bin as COLMAP writes it; the model must be one of CAMERA_MODELS."""
    parts = [COUNT.pack(len(cameras))]
    for camera in cameras:
        if camera.model not in MODEL_IDS:
            raise ValueError(f"unknown COLMAP camera model {camera.model!r}")
        model_id, count = MODEL_IDS[camera.model]
        if len(camera.params) != count:
            raise ValueError(f"{camera.model} takes {count} parameters, got {len(camera.params)}")
        parts += [
            CAMERA_HEAD.pack(camera.camera_id, model_id, camera.width, camera.height),
            struct.pack(f"<{count}d", *camera.params),
        ]
    Path(path).write_bytes(b"".join(parts))


def write_model(
    folder: Path,
    cameras: Sequence[ColmapCamera],
    images: Sequence[ColmapImage],
    binary: bool = True,
) -> None:
    """cameras and images files of a sparse model (and an empty points3D, so that
    COLMAP itself opens the folder)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    if binary:
        write_cameras_binary(folder / "cameras.bin", cameras)
        write_images_binary(folder / "images.bin", images)
        (folder / "points3D.bin").write_bytes(COUNT.pack(0))
    else:
        write_cameras_text(folder / "cameras.txt", cameras)
        write_images_text(folder / "images.txt", images)
        (folder / "points3D.txt").write_text(
            "# 3D point list with one line of data per point:\n"
            "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
            "# Number of points: 0, mean track length: 0\n"
        )
