"""COLMAP reconstructions as a dataset (`dataset=colmap`): poses of the registered images.

COLMAP stores, per image, the world-to-camera transform x_camera = R x_world + t, with
R as a unit quaternion (w first). relocfw keeps camera-to-world poses, so at the door
the position becomes the camera centre C = -R^T t and the rotation R^T (the conjugate
quaternion). Both use the same camera axes (x right, y down, z forward: OpenCV's, as
7-Scenes and TUM), so no axis is flipped.

A COLMAP model has no scale of its own: positions come out in model units, not metres,
unless the model was aligned to metric coordinates (e.g. `colmap model_aligner`).

Each frame's `camera` is its COLMAP camera as a pinhole (PINHOLE, SIMPLE_PINHOLE, or a
distortion model whose coefficients are all 0), None for a camera with lens distortion
(`ColmapDataset.why_no_camera(name)` says why); a model has no depth maps. With
`points=True` (the default) each frame also carries the model's 3-D points it observed
(`Frame.observations`, relocfw.data.colmap_points), so refine=features solves against
COLMAP's own tracks instead of triangulating again.
"""

from __future__ import annotations

import fnmatch
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import (
    QUATERNION_MINIMUM,
    QUATERNION_TOLERANCE,
    conjugate,
    quaternion_to_matrix,
)
from relocfw.core.values import Pose
from relocfw.data.colmap_cameras import (
    images_with_cameras,
    model_cameras_file,
    pinhole_of,
    read_model_cameras,
    why_not_pinhole,
)
from relocfw.data.colmap_format import (
    ColmapCamera,
    ColmapImage,
    read_images_binary,
    read_images_text,
)
from relocfw.data.colmap_points import read_model_observations
from relocfw.data.frames import Frame
from relocfw.data.on_error import OnError

UNITS_NOTE = "positions are in COLMAP model units (arbitrary scale), not metres"
SPLITS = ("train", "test")
GLOB_CHARACTERS = re.compile(r"[*?\[]")


def colmap_to_pose(
    qvec: Sequence[float], tvec: Sequence[float], source: str = "COLMAP pose"
) -> Pose:
    """relocfw's camera-to-world pose of COLMAP's world-to-camera (qvec, tvec).

    Args:
        qvec: world-to-camera rotation (QW, QX, QY, QZ).
        tvec: world-to-camera translation (TX, TY, TZ).
        source: what to name in an error (file and line, or file and image).

    Raises:
        DataError: NaN or infinite values, or a quaternion whose norm is not 1.
    """
    q = np.asarray(qvec, dtype=np.float64).reshape(-1)
    t = np.asarray(tvec, dtype=np.float64).reshape(-1)
    if q.shape != (4,) or t.shape != (3,) or not np.all(np.isfinite(np.r_[q, t])):
        raise DataError(
            f"{source}: pose must be 4 + 3 finite numbers (QW QX QY QZ TX TY TZ), "
            f"got {q.tolist()} {t.tolist()}"
        )
    norm = float(np.linalg.norm(q))
    # Stricter than geometry.checked_quaternion (which normalises with a warning):
    # COLMAP writes unit quaternions at full precision, so a norm this far from 1
    # means a damaged or mis-edited file, not rounding.
    if norm < QUATERNION_MINIMUM or abs(norm - 1.0) > QUATERNION_TOLERANCE:
        raise DataError(
            f"{source}: quaternion QW QX QY QZ = {q.tolist()} has norm {norm:.6g}, not 1 "
            "(COLMAP writes unit quaternions)"
        )
    q = q / norm
    world_to_camera = quaternion_to_matrix(q)
    return Pose(-world_to_camera.T @ t, conjugate(q))


def pose_to_colmap(pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """COLMAP's world-to-camera (qvec, tvec) of a camera-to-world pose; qvec has w >= 0."""
    world_to_camera = quaternion_to_matrix(pose.quaternion).T
    return conjugate(pose.quaternion), -world_to_camera @ pose.position


def model_images_file(folder: Path, root: Path | None = None) -> Path:
    """images.bin, or images.txt, of a sparse model folder (binary first, as COLMAP).

    When there is none, the error lists the model folders found below `root` (or
    `folder`), so a layout other than root/sparse/0 is one option away.
    """
    folder = Path(folder)
    for name in ("images.bin", "images.txt"):
        if (folder / name).is_file():
            return folder / name
    base = Path(root) if root is not None else folder
    found = sorted(
        {
            str(p.parent.relative_to(base))
            for pattern in ("images.bin", "*/images.bin", "*/*/images.bin", "*/*/*/images.bin")
            for p in [*base.glob(pattern), *base.glob(pattern.replace(".bin", ".txt"))]
        }
    )
    hint = f" (models found in {base}: {', '.join(found[:5])})" if found else ""
    if not folder.is_dir():
        raise DataError(f"dataset.model: COLMAP model folder not found: {folder}{hint}")
    raise DataError(f"{folder}: not a COLMAP sparse model: no images.bin or images.txt{hint}")


def read_model_images(path: Path, on_error: OnError | None = None) -> list[ColmapImage]:
    """Images of an images.bin or images.txt; duplicate ids or names are refused."""
    path = Path(path)
    on_error = on_error or OnError()
    binary = path.suffix == ".bin"
    images = read_images_binary(path) if binary else read_images_text(path, on_error)
    seen_ids: dict[int, str] = {}
    seen_names: dict[str, str] = {}
    unique = []
    for image in images:
        try:
            if image.image_id in seen_ids:
                raise DataError(
                    f"{image.source}: duplicate IMAGE_ID {image.image_id} "
                    f"(first at {seen_ids[image.image_id]})"
                )
            if image.name in seen_names:
                raise DataError(
                    f"{image.source}: duplicate image NAME {image.name!r} "
                    f"(first at {seen_names[image.name]})"
                )
        except DataError as error:
            on_error.handle(error)
            continue
        seen_ids[image.image_id] = image.source
        seen_names[image.name] = image.source
        unique.append(image)
    if not unique:
        raise DataError(f"{path}: no registered images")
    return unique


def split_entries(value: object, key: str, root: Path) -> list[tuple[str, str]]:
    """(name or pattern, where it was given) pairs of a `dataset.train`/`test` value.

    Args:
        value: a list of image names / fnmatch patterns, or the path of a text file
            (relative to root) listing one per line (# comments and blank lines skipped).
        key: the option, for messages ("dataset.train").
        root: the dataset folder.
    """
    if isinstance(value, str):
        path = Path(value).expanduser()
        path = path if path.is_absolute() else root / path
        if not path.is_file():
            raise DataError(
                f"{key}: list file not found: {path} (to give names or patterns "
                f"directly, pass a list: {key}='[seq1/*]')"
            )
        entries = []
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
            text = line.strip()
            if text and not text.startswith("#"):
                entries.append((text, f"{path}:{number}"))
        if not entries:
            raise DataError(f"{path}: lists no images ({key})")
        return entries
    if not isinstance(value, Sequence) or not value:
        raise ConfigError(
            f"{key} must be a non-empty list of image names or patterns such as "
            f"['seq1/*'], or a list file, got {value!r}"
        )
    entries = []
    for item in value:
        if not isinstance(item, str) or not item:
            raise ConfigError(f"{key}: image names and patterns are strings, got {item!r}")
        entries.append((item, key))
    return entries


def select_images(
    images: Sequence[ColmapImage],
    entries: Sequence[tuple[str, str]],
    model_file: Path,
    on_error: OnError,
) -> set[str]:
    """Names of the images an entry list selects, each entry by exact name or fnmatch.

    An entry that selects nothing is an error (a typo, or an image COLMAP did not
    register), handled by `on_error`.
    """
    names = [image.name for image in images]
    known = set(names)
    chosen: set[str] = set()
    for entry, source in entries:
        if entry in known:
            chosen.add(entry)
            continue
        matched = []
        if GLOB_CHARACTERS.search(entry):
            pattern = re.compile(fnmatch.translate(entry))
            matched = [name for name in names if pattern.match(name)]
        if not matched:
            on_error.handle(
                DataError(f"{source}: {entry!r} matches no image registered in {model_file}")
            )
        chosen.update(matched)
    return chosen


class ColmapDataset:
    """A COLMAP reconstruction: images with the poses COLMAP estimated for them.

    Args:
        root: the project folder.
        train: images to map: names or fnmatch patterns on COLMAP's image NAME
            (e.g. ["seq1/*", "seq2/*"]), or a text file listing them one per line
            (relative to root). None: every registered image not in test.
        test: images to relocalize, given the same way. None: every image not in train.
        model: the sparse model folder, relative to root (images.bin or images.txt;
            binary is read when both are there, as COLMAP does).
        images: the image folder, relative to root; COLMAP's NAMEs are relative to it.
        on_error: "fail" or "skip" (bad entries left out and listed).
        metric: True declares the model metric (aligned to metres, e.g. with
            `colmap model_aligner`): reports then say metres and print no note.
        points: read the model's points3D and each image's observations of them into
            `Frame.observations` (False: poses only; a model without points3D gives
            none either way).

    Attributes:
        metric: False by default: COLMAP's scale is arbitrary, so errors are in
            model units.
        units_note: one line saying so, for reports; "" for a metric model.
        cameras: the model's cameras (checked intrinsics) by CAMERA_ID; `camera(name)`
            gives the one an image was taken with.
        cameras_file: the cameras.bin or cameras.txt they were read from.
        pinholes: each camera as a PinholeCamera (None with lens distortion), by
            CAMERA_ID: the frames' `camera`.
    """

    metric: bool = False
    units_note: str = UNITS_NOTE

    def __init__(
        self,
        root: str | None = None,
        train: str | Sequence[str] | None = None,
        test: str | Sequence[str] | None = None,
        model: str = "sparse/0",
        images: str = "images",
        on_error: str = "fail",
        metric: bool = False,
        points: bool = True,
    ) -> None:
        if not isinstance(metric, bool):
            raise ConfigError(f"dataset.metric must be true or false, got {metric!r}")
        if not isinstance(points, bool):
            raise ConfigError(f"dataset.points must be true or false, got {points!r}")
        # Read by relocfw.report.units.unit_of: what every report calls the positions.
        self.metric = metric
        self.units_note = "" if metric else UNITS_NOTE
        if root is None or str(root) == "":
            raise ConfigError("dataset.root is not set: pass dataset.root=DIR")
        self.root = Path(root).expanduser()
        if not self.root.is_dir():
            raise DataError(f"dataset.root: folder not found: {self.root}")
        if train is None and test is None:
            raise ConfigError(
                "dataset.train / dataset.test: name the images of at least one split, "
                "e.g. dataset.test='[seq3/*]' (the other split is then every other image)"
            )
        self.on_error = OnError(on_error)
        self.model_file = model_images_file(self.root / model, self.root)
        self.image_folder = self.root / images
        if not self.image_folder.is_dir():
            raise DataError(f"dataset.images: image folder not found: {self.image_folder}")
        self.cameras_file = model_cameras_file(self.model_file)
        self.cameras = read_model_cameras(self.cameras_file, self.on_error)
        registered = images_with_cameras(
            read_model_images(self.model_file, self.on_error),
            self.cameras,
            self.cameras_file,
            self.on_error,
        )
        self._camera_ids = {image.name: image.camera_id for image in registered}
        self.pinholes = {key: pinhole_of(camera) for key, camera in self.cameras.items()}
        # Read after the poses, so a damaged images file is named by their reader.
        self._observations = read_model_observations(self.model_file) if points else {}
        chosen = self._splits(registered, {"train": train, "test": test})
        self._frames = {
            split: self._existing_frames([i for i in registered if i.name in chosen[split]])
            for split in SPLITS
        }

    def _splits(
        self, images: Sequence[ColmapImage], values: dict[str, object]
    ) -> dict[str, set[str]]:
        chosen: dict[str, set[str]] = {}
        for split, value in values.items():
            if value is not None:
                entries = split_entries(value, f"dataset.{split}", self.root)
                chosen[split] = select_images(images, entries, self.model_file, self.on_error)
        everything = {image.name for image in images}
        for split, other in (("train", "test"), ("test", "train")):
            if split not in chosen:
                chosen[split] = everything - chosen[other]
        shared = sorted(chosen["train"] & chosen["test"])
        if shared:
            raise ConfigError(
                f"dataset.train and dataset.test share {len(shared)} images "
                f"({', '.join(shared[:3])}{', ...' if len(shared) > 3 else ''}): "
                "a test image would be in the map"
            )
        return chosen

    def _existing_frames(self, images: Sequence[ColmapImage]) -> list[Frame]:
        """Frames in name order; a registered image missing on disk goes to on_error."""
        frames = []
        for image in sorted(images, key=lambda i: i.name):
            path = self.image_folder / image.name
            try:
                if not path.is_file():
                    raise DataError(f"{image.source}: image {image.name!r} not found: {path}")
                pose = colmap_to_pose(image.qvec, image.tvec, image.source)
            except DataError as error:
                self.on_error.handle(error)
                continue
            frames.append(
                Frame(
                    image.name,
                    path,
                    pose,
                    camera=self.pinholes[image.camera_id],
                    observations=self._observations.get(image.name),
                )
            )
        return frames

    def frames(self, split: str) -> list[Frame]:
        if split not in SPLITS:
            raise ConfigError(f"split must be 'train' or 'test', got {split!r}")
        return list(self._frames[split])

    def split_source(self, split: str) -> str:
        """What lists the split's frames, for messages: the model's images file."""
        return f"dataset.{split} of {self.model_file}"

    def camera(self, name: str) -> ColmapCamera:
        """The camera (intrinsics) image `name` (a Frame's name) was taken with."""
        if name not in self._camera_ids:
            raise DataError(f"{name!r} is not an image registered in {self.model_file}")
        return self.cameras[self._camera_ids[name]]

    def why_no_camera(self, name: str) -> str:
        """Why frame `name` has no pinhole camera, in one line ("" when it has one).

        E.g. "camera 3 is OPENCV with lens distortion (-0.1 0.01 0 0)", for a message
        such as "structure-based refinement needs undistorted images: ...".
        """
        return why_not_pinhole(self.camera(name))
