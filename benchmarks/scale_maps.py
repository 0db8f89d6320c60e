"""What benchmarks/structure_scale.py builds its maps with: the real build (one worker,
OpenCV's threads, or a process pool), copies of the real map under rigid transforms,
and the global descriptors its retrieval searches."""

from __future__ import annotations

import multiprocessing
import os
import resource
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import torch
from structure_query import LazyViews, thumbnail

from relocfw.core.geometry import matrix_to_quaternion, quaternion_to_matrix
from relocfw.core.values import Pose
from relocfw.data.sevenscenes import SceneCameras
from relocfw.structure import StructureMap, build_from_depth
from relocfw.structure.compact_writer import CompactMapWriter, camera_frame
from relocfw.structure.descriptor_codes import DescriptorCodec

# Copies sit on a grid this far apart (metres): a building's rooms, each a rigid
# transform of the real one. Red Kitchen's map spans about 2 m.
COPY_SPACING_M = 30.0
COPIES_PER_ROW = 16
# The copy signature's length against the unit thumbnail: large enough that every
# image of the query's copy is nearer than any image of another copy (squared
# distances: at most 4 within a copy, about 2 x 2^2 = 8 between copies).
SIGNATURE_SCALE = 2.0
THUMBNAIL_DIMENSIONS = 192  # structure_query.THUMBNAIL, 16 x 12


def cpu_seconds() -> float:
    """CPU time of this process and its finished children."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def merged(maps: list[StructureMap]) -> StructureMap:
    """The maps' images in order, as one map."""
    return StructureMap(
        features=tuple(f for m in maps for f in m.features),
        points=tuple(p for m in maps for p in m.points),
        poses=tuple(p for m in maps for p in m.poses),
        cameras=tuple(c for m in maps for c in m.cameras),
        names=tuple(n for m in maps for n in m.names),
        source=maps[0].source,
        skipped_views=tuple(s for m in maps for s in m.skipped_views),
    )


def single_threaded_worker() -> None:
    """A pool worker's threads: one each, so the pool's workers share the cores."""
    cv2.setNumThreads(1)
    torch.set_num_threads(1)


def warm_up(seconds: float) -> None:
    """A pool task that holds its worker a moment, so every worker starts (and
    imports this module) before the timed tasks."""
    time.sleep(seconds)


def build_part(
    frames: list, cameras: SceneCameras, max_features: int, image_scale: float = 1.0
) -> StructureMap:
    """build_from_depth of some frames (a pool task)."""
    views = LazyViews(frames, cameras)
    return build_from_depth(views, max_features=max_features, quiet=True, image_scale=image_scale)


def timed_build(
    frames: list,
    cameras: SceneCameras,
    max_features: int,
    workers: int,
    opencv_threads: int,
    image_scale: float = 1.0,
) -> tuple[StructureMap, dict]:
    """The real build of `frames`, timed: in this process with `opencv_threads` OpenCV
    threads (workers = 1), or split over a pool of `workers` processes of one thread
    each, the parts merged in order."""
    start_cpu = cpu_seconds()
    start = time.perf_counter()
    if workers == 1:
        cv2.setNumThreads(opencv_threads)
        structure = build_part(frames, cameras, max_features, image_scale)
    else:
        # Small tasks, several per worker, so no worker idles at the end. spawn, not
        # fork: a fork copies OpenCV's thread pool after the one-worker builds used it,
        # and the children then wait forever on its locks (seen: workers asleep on a
        # futex). The workers start and import before the clock starts again (their
        # CPU time, counted when they end, still holds that start-up).
        step = max(1, len(frames) // (4 * workers))
        parts = [frames[i : i + step] for i in range(0, len(frames), step)]
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(workers, context, initializer=single_threaded_worker) as pool:
            for started in [pool.submit(warm_up, 1.0) for _ in range(workers)]:
                started.result()
            start_cpu = cpu_seconds()
            start = time.perf_counter()
            futures = [
                pool.submit(build_part, part, cameras, max_features, image_scale) for part in parts
            ]
            structure = merged([future.result() for future in futures])
    seconds = time.perf_counter() - start
    return structure, {
        "workers": workers,
        "opencv_threads": opencv_threads if workers == 1 else 1,
        "images": len(frames),
        "seconds": seconds,
        "cpu_seconds": cpu_seconds() - start_cpu,
        "images_per_second": len(frames) / seconds,
    }


def copy_transform(copy: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Copy `copy`'s rigid transform (rotation, translation) of the real scene; copy 0
    is the scene itself. The rotation is random (seeded per copy): the points and
    poses of a copy are genuinely other coordinates, not a shift of the same ones."""
    if copy == 0:
        return np.eye(3), np.zeros(3)
    rng = np.random.default_rng([seed, copy])
    quaternion = rng.standard_normal(4)
    rotation = quaternion_to_matrix(quaternion / np.linalg.norm(quaternion))
    row, column = divmod(copy, COPIES_PER_ROW)
    return rotation, np.array([column * COPY_SPACING_M, row * COPY_SPACING_M, 0.0])


def placed(pose: Pose, rotation: np.ndarray, translation: np.ndarray) -> Pose:
    """A camera-to-world pose moved with the scene by the rigid transform."""
    turned = rotation @ quaternion_to_matrix(pose.quaternion)
    return Pose(rotation @ pose.position + translation, matrix_to_quaternion(turned))


def base_rows(structure: StructureMap, codec: DescriptorCodec) -> list[tuple]:
    """Per image of the real map: its rows with a 3-D point, coded, and their points in
    the camera frame (what every copy of the image writes again)."""
    rows = []
    for features, points, pose in zip(
        structure.features, structure.points, structure.poses, strict=True
    ):
        kept = np.isfinite(points).all(axis=1)
        rows.append((codec.encode(features.descriptors[kept]), camera_frame(points[kept], pose)))
    return rows


def write_copies(
    folder: Path,
    structure: StructureMap,
    rows: list[tuple],
    codec: DescriptorCodec,
    size: int,
    point_dtype: str,
    seed: int,
) -> float:
    """Write a compact map of `size` images: copies 0, 1, ... of the real map, each a
    rigid transform of it (poses moved; the camera-frame points move with them), the
    last copy cut short. Returns the seconds the write took."""
    base = len(structure)
    counts = [len(rows[i % base][0]) for i in range(size)]
    start = time.perf_counter()
    with CompactMapWriter(folder, counts, codec, structure.source, point_dtype) as writer:
        for index in range(size):
            copy, frame = divmod(index, base)
            if frame == 0:
                rotation, translation = copy_transform(copy, seed)
            codes, points = rows[frame]
            pose = placed(structure.poses[frame], rotation, translation)
            name = f"{structure.names[frame]}#c{copy}"
            writer.add(codes, points, pose, structure.cameras[frame], name)
    return time.perf_counter() - start


def signature(copy: int, dimensions: int, seed: int) -> np.ndarray:
    """Copy `copy`'s random unit signature of `dimensions`, times SIGNATURE_SCALE."""
    vector = np.random.default_rng([seed, copy, 1]).standard_normal(dimensions)
    return (SIGNATURE_SCALE * vector / np.linalg.norm(vector)).astype(np.float32)


def map_descriptors(thumbnails: np.ndarray, size: int, dimensions: int, seed: int) -> np.ndarray:
    """[size, dimensions] float32 global descriptors of the copied map: image (copy c,
    frame f) is [thumbnail of f, signature of c]."""
    base = len(thumbnails)
    descriptors = np.empty((size, dimensions), dtype=np.float32)
    for start in range(0, size, base):
        stop = min(start + base, size)
        descriptors[start:stop, :THUMBNAIL_DIMENSIONS] = thumbnails[: stop - start]
        rest = dimensions - THUMBNAIL_DIMENSIONS
        descriptors[start:stop, THUMBNAIL_DIMENSIONS:] = signature(start // base, rest, seed)
    return descriptors


def query_descriptor(image: np.ndarray, copy: int, dimensions: int, seed: int) -> np.ndarray:
    """A query seen in copy `copy`: [its thumbnail, the copy's signature]."""
    rest = dimensions - THUMBNAIL_DIMENSIONS
    return np.concatenate([thumbnail(image), signature(copy, rest, seed)]).astype(np.float32)


def evict_from_cache(paths: list[Path]) -> None:
    """Ask the kernel to drop the files' pages from its cache, so the next read comes
    from the disk (a map larger than memory); pages mapped by a live map stay."""
    for path in paths:
        handle = os.open(path, os.O_RDONLY)
        try:
            os.posix_fadvise(handle, 0, 0, os.POSIX_FADV_DONTNEED)
        finally:
            os.close(handle)
