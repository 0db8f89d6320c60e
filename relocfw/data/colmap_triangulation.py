"""A COLMAP sparse model of images whose poses are known, made with pycolmap.

What hloc does for 7-Scenes and what COLMAP calls "triangulation from known poses":
SIFT features of every image, matches between pairs with two-view geometric
verification, then tracks triangulated with the poses held fixed and bundle adjusted
over the points only (pycolmap.triangulate_points). The result is a model folder
`dataset=colmap` reads like any other, with points3D: the tests and
benchmarks/colmap_points.py make theirs with it, and a user with posed images and no
COLMAP model can too. pycolmap is optional (`pip install pycolmap`).
"""

from __future__ import annotations

import importlib
import shutil
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.values import Pose
from relocfw.data.colmap import pose_to_colmap
from relocfw.data.colmap_format import ColmapCamera, ColmapImage, write_model

PAIRINGS = ("exhaustive", "sequential")


def pycolmap_module() -> ModuleType:
    """pycolmap, or a ConfigError saying how to install it."""
    try:
        return importlib.import_module("pycolmap")
    except ImportError:
        raise ConfigError(
            "building a COLMAP model needs pycolmap: pip install 'pycolmap>=3.12'"
        ) from None


def image_pairs(
    names: Sequence[str], unmatched: Sequence[str], pairing: str, overlap: int
) -> list[tuple[str, str]]:
    """The pairs of images to match: every pair ("exhaustive") or each image with the
    next `overlap` in name order ("sequential"), leaving out the `unmatched`."""
    left_out = set(unmatched)
    matched = sorted(name for name in names if name not in left_out)
    window = len(matched) if pairing == "exhaustive" else overlap
    return [
        (first, second)
        for index, first in enumerate(matched)
        for second in matched[index + 1 : index + 1 + window]
    ]


def triangulate_posed_images(
    image_root: Path,
    names: Sequence[str],
    poses: Sequence[Pose],
    camera: ColmapCamera,
    workspace: Path,
    max_features: int = 2048,
    pairing: str = "exhaustive",
    overlap: int = 10,
    threads: int = 2,
    unmatched: Sequence[str] = (),
) -> Path:
    """Triangulate a sparse model of `names` (relative to `image_root`) at `poses`.

    Args:
        image_root: the folder COLMAP's image NAMEs are relative to.
        names: the images, e.g. "seq-01/frame-000000.color.jpg".
        poses: their camera-to-world poses (relocfw's convention).
        camera: the one camera of all of them (COLMAP's convention: a PINHOLE's cx
            is measured from the image's corner).
        workspace: a folder for the feature database and the model (emptied first).
        max_features: SIFT features per image.
        pairing: "exhaustive" (every pair of images) or "sequential" (each image with
            the next `overlap` in name order: cheaper for long recordings).
        overlap: the sequential pairing's window.
        threads: CPU threads for extraction and matching.
        unmatched: images of `names` registered at their pose but matched with
            none, so they add no observation and no point: queries that an
            evaluation must not have in the map, yet needs in the model (dataset=
            colmap reads both splits from one model).

    Returns:
        The model folder (workspace/sparse), binary cameras, images and points3D.

    Raises:
        ConfigError: without pycolmap, or on an unknown pairing.
        DataError: when names and poses differ in length, or COLMAP registers an image
            relocfw did not ask for.
    """
    pycolmap = pycolmap_module()
    if pairing not in PAIRINGS:
        raise ConfigError(f"pairing must be one of {', '.join(PAIRINGS)}, got {pairing!r}")
    if len(names) != len(poses) or not names:
        raise DataError(f"{len(names)} image names but {len(poses)} poses; one pose per image")
    workspace = Path(workspace)
    shutil.rmtree(workspace, ignore_errors=True)
    workspace.mkdir(parents=True)
    database = workspace / "database.db"
    reader = pycolmap.ImageReaderOptions(
        camera_model=camera.model, camera_params=",".join(repr(v) for v in camera.params)
    )
    extraction = pycolmap.FeatureExtractionOptions(num_threads=threads)
    extraction.sift.max_num_features = max_features
    pycolmap.extract_features(
        database,
        Path(image_root),
        image_names=list(names),
        camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    pairs = workspace / "pairs.txt"
    pairs.write_text(
        "".join(f"{a} {b}\n" for a, b in image_pairs(names, unmatched, pairing, overlap)),
        encoding="utf-8",
    )
    pycolmap.match_image_pairs(
        database,
        matching_options=pycolmap.FeatureMatchingOptions(num_threads=threads),
        pairing_options=pycolmap.ImportedPairingOptions(match_list_path=str(pairs)),
        device=pycolmap.Device.cpu,
    )
    # The database numbers images and cameras; the posed model must use its numbers.
    store = pycolmap.Database.open(str(database))
    try:
        stored_images = store.read_all_images()
        stored_cameras = store.read_all_cameras()
    finally:
        store.close()
    pose_of = dict(zip(names, poses, strict=True))
    images = []
    for stored in stored_images:
        if stored.name not in pose_of:
            raise DataError(
                f"{database}: COLMAP holds image {stored.name!r}, which was not asked for"
            )
        qvec, tvec = pose_to_colmap(pose_of[stored.name])
        images.append(
            ColmapImage(stored.image_id, tuple(qvec), tuple(tvec), stored.camera_id, stored.name)
        )
    cameras = [
        ColmapCamera(c.camera_id, camera.model, c.width, c.height, tuple(c.params))
        for c in stored_cameras
    ]
    write_model(workspace / "posed", cameras, images, binary=True)
    posed = pycolmap.Reconstruction(str(workspace / "posed"))
    model = workspace / "sparse"
    model.mkdir()
    pycolmap.triangulate_points(posed, database, Path(image_root), model)
    return model
