"""COLMAP's points3D and the images' observations of them (relocfw.data.colmap_points),
on models pycolmap writes, text and binary, and on damaged files."""

from __future__ import annotations

import shutil
import struct
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from relocfw.core.errors import DataError
from relocfw.core.values import Pose
from relocfw.data.colmap import ColmapDataset, pose_to_colmap
from relocfw.data.colmap_format import ColmapCamera, ColmapImage, write_model
from relocfw.data.colmap_points import (
    read_model_observations,
    read_points3d_binary,
    read_points3d_text,
)

pycolmap = pytest.importorskip(
    "pycolmap", reason="pycolmap writes the models (pip install pycolmap)"
)

WIDTH, HEIGHT, FOCAL = 80, 60, 60.0
CAMERA = ColmapCamera(1, "PINHOLE", WIDTH, HEIGHT, (FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2))
POSITIONS = [(-0.3, 0.0, 0.0), (-0.1, 0.05, 0.0), (0.1, 0.0, 0.05), (0.3, -0.05, 0.0)]


def project(world: np.ndarray, position: np.ndarray) -> np.ndarray:
    """COLMAP pixels of world points seen from an unrotated camera at `position`."""
    in_camera = world - position
    return FOCAL * in_camera[:, :2] / in_camera[:, 2:] + np.array([WIDTH / 2, HEIGHT / 2])


@pytest.fixture(scope="module")
def model(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A model pycolmap writes: 4 posed images, the points seen by two or more, and
    unobserved 2-D points among the observed ones; plus what each image should read."""
    folder = tmp_path_factory.mktemp("colmap_points")
    rng = np.random.default_rng(0)
    world = np.column_stack(
        [rng.uniform(-1.5, 1.5, 300), rng.uniform(-1.0, 1.0, 300), rng.uniform(2.0, 4.0, 300)]
    )
    poses = [Pose(np.array(p), np.array([1.0, 0.0, 0.0, 0.0])) for p in POSITIONS]
    images = []
    for number, pose in enumerate(poses, start=1):
        qvec, tvec = pose_to_colmap(pose)
        images.append(ColmapImage(number, tuple(qvec), tuple(tvec), 1, f"view{number}.png"))
    write_model(folder / "posed", [CAMERA], images)
    reconstruction = pycolmap.Reconstruction(str(folder / "posed"))
    seen = []
    for pose in poses:
        pixels = project(world, pose.position)
        seen.append((pixels >= 0).all(axis=1) & (pixels < [WIDTH, HEIGHT]).all(axis=1))
    tracked = np.flatnonzero(np.sum(seen, axis=0) >= 2)
    # Per image, its 2-D points in a shuffled order: observed and unobserved mixed.
    rows_of = []
    for number, pose in enumerate(poses, start=1):
        visible = np.flatnonzero(seen[number - 1])
        order = rng.permutation(visible)
        pixels = project(world[order], pose.position)
        reconstruction.image(number).points2D = pycolmap.Point2DList(
            [pycolmap.Point2D(np.array(p)) for p in pixels]
        )
        rows_of.append({int(point): index for index, point in enumerate(order)})
    expected: dict[str, dict[int, tuple[np.ndarray, np.ndarray]]] = {
        image.name: {} for image in images
    }
    for point in tracked.tolist():
        point_id = reconstruction.add_point3D(world[point], pycolmap.Track(), np.zeros(3, np.uint8))
        for number, pose in enumerate(poses, start=1):
            if seen[number - 1][point]:
                index = rows_of[number - 1][point]
                reconstruction.add_observation(point_id, pycolmap.TrackElement(number, index))
                pixel = project(world[point][None], pose.position)[0]
                expected[f"view{number}.png"][point_id] = (pixel - 0.5, world[point])
    for kind in ("bin", "txt"):
        (folder / kind).mkdir()
    reconstruction.write_binary(str(folder / "bin"))
    reconstruction.write_text(str(folder / "txt"))
    return {"folder": folder, "expected": expected, "tracked": len(tracked)}


@pytest.mark.parametrize("kind", ["bin", "txt"])
def test_each_image_reads_the_points_it_observed(model, kind):
    observations = read_model_observations(model["folder"] / kind / f"images.{kind}")
    assert set(observations) == set(model["expected"])
    total = 0
    for name, wanted in model["expected"].items():
        found = observations[name]
        assert sorted(found.track_ids.tolist()) == sorted(wanted)  # the -1 rows left out
        for row, track in enumerate(found.track_ids.tolist()):
            pixel, point = wanted[track]
            # Half a pixel less than COLMAP's: relocfw measures from the pixel's centre.
            np.testing.assert_allclose(found.keypoints[row], pixel, atol=1e-9)
            np.testing.assert_allclose(found.points[row], point, atol=1e-9)
        total += len(found)
    assert total >= 2 * model["tracked"] > 100


def test_text_and_binary_read_the_same(model):
    binary = read_model_observations(model["folder"] / "bin" / "images.bin")
    text = read_model_observations(model["folder"] / "txt" / "images.txt")
    for name in binary:
        np.testing.assert_array_equal(binary[name].track_ids, text[name].track_ids)
        np.testing.assert_allclose(binary[name].keypoints, text[name].keypoints, atol=1e-9)
        np.testing.assert_allclose(binary[name].points, text[name].points, atol=1e-9)
    points = read_points3d_binary(model["folder"] / "bin" / "points3D.bin")
    assert len(points) == model["tracked"]
    np.testing.assert_array_equal(
        points.ids, read_points3d_text(model["folder"] / "txt" / "points3D.txt").ids
    )


def test_images_sharing_a_point_share_its_coordinates(model):
    observations = read_model_observations(model["folder"] / "bin" / "images.bin")
    where: dict[int, np.ndarray] = {}
    shared = 0
    for found in observations.values():
        for track, point in zip(found.track_ids.tolist(), found.points, strict=True):
            if track in where:
                np.testing.assert_array_equal(where[track], point)
                shared += 1
            where[track] = point
    assert shared >= model["tracked"]


def project_folder(model: dict, kind: str, tmp_path: Path) -> Path:
    """A dataset=colmap folder around one of the written models, with tiny images."""
    root = tmp_path / "project"
    shutil.copytree(model["folder"] / kind, root / "sparse" / "0")
    (root / "images").mkdir()
    for name in model["expected"]:
        cv2.imwrite(str(root / "images" / name), np.zeros((HEIGHT, WIDTH, 3), np.uint8))
    return root


@pytest.mark.parametrize("kind", ["bin", "txt"])
def test_dataset_frames_carry_observations_unless_points_is_false(model, kind, tmp_path):
    root = project_folder(model, kind, tmp_path)
    dataset = ColmapDataset(str(root), test=["view4.png"])
    frames = dataset.frames("train") + dataset.frames("test")
    for frame in frames:
        assert len(frame.observations) == len(model["expected"][frame.name])
    assert frames[0] == frames[0]  # observations do not break comparing frames
    poses_only = ColmapDataset(str(root), test=["view4.png"], points=False)
    assert all(f.observations is None for f in poses_only.frames("train"))


# --- damaged files: one DataError naming the file and the line or record ----------


def damaged_copy(model: dict, kind: str, tmp_path: Path) -> Path:
    folder = tmp_path / kind
    shutil.copytree(model["folder"] / kind, folder)
    return folder


def test_a_truncated_points3d_bin_names_the_file_and_the_point(model, tmp_path):
    folder = damaged_copy(model, "bin", tmp_path)
    data = (folder / "points3D.bin").read_bytes()
    (folder / "points3D.bin").write_bytes(data[: len(data) - 5])
    with pytest.raises(DataError, match=r"points3D\.bin: truncated or corrupt .*point \d+ of"):
        read_model_observations(folder / "images.bin")


def test_an_impossible_point_count_is_a_corrupt_header(model, tmp_path):
    folder = damaged_copy(model, "bin", tmp_path)
    data = bytearray((folder / "points3D.bin").read_bytes())
    data[:8] = struct.pack("<Q", 10**12)
    (folder / "points3D.bin").write_bytes(bytes(data))
    with pytest.raises(DataError, match=r"points3D\.bin: corrupt header: 1000000000000 points"):
        read_points3d_binary(folder / "points3D.bin")


def test_a_truncated_images_bin_names_the_file(model, tmp_path):
    folder = damaged_copy(model, "bin", tmp_path)
    data = (folder / "images.bin").read_bytes()
    (folder / "images.bin").write_bytes(data[:-30])
    with pytest.raises(
        DataError, match=r"images\.bin: truncated or corrupt .*2-D points of image 4"
    ):
        read_model_observations(folder / "images.bin")


def test_a_nan_coordinate_names_the_line(model, tmp_path):
    folder = damaged_copy(model, "txt", tmp_path)
    lines = (folder / "points3D.txt").read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    fields = lines[first].split()
    lines[first] = " ".join([fields[0], "nan", *fields[2:]])
    (folder / "points3D.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=rf"points3D\.txt:{first + 1}: point {fields[0]} has a NaN"):
        read_model_observations(folder / "images.txt")


def test_a_point_an_image_names_but_points3d_lacks_is_refused(model, tmp_path):
    folder = damaged_copy(model, "txt", tmp_path)
    lines = (folder / "points3D.txt").read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    missing = lines.pop(first).split()[0]
    (folder / "points3D.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(
        DataError, match=rf"images\.txt:\d+: refers to POINT3D_ID {missing}, which .*points3D\.txt"
    ):
        read_model_observations(folder / "images.txt")


def test_a_points2d_line_that_is_not_triples_names_the_line(model, tmp_path):
    folder = damaged_copy(model, "txt", tmp_path)
    lines = (folder / "images.txt").read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    lines[first + 1] = lines[first + 1].rstrip() + " 12.5"
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=rf"images\.txt:{first + 2}: POINTS2D holds"):
        read_model_observations(folder / "images.txt")


def test_a_damaged_points_file_stops_the_dataset_with_one_error(model, tmp_path):
    root = project_folder(model, "bin", tmp_path)
    points = root / "sparse" / "0" / "points3D.bin"
    points.write_bytes(points.read_bytes()[:20])
    with pytest.raises(DataError, match=r"points3D\.bin"):
        ColmapDataset(str(root), test=["view4.png"])


def test_a_model_of_1e5_points_is_read_in_bulk(tmp_path):
    # Written here with numpy (pycolmap would take longer than the read): every point
    # with a track of 2, ids in reverse so the reader's sort is exercised.
    count = 100_000
    record = np.dtype(
        [("id", "<u8"), ("xyz", "<f8", 3), ("rgb", "u1", 3), ("error", "<f8"),
         ("length", "<u8"), ("track", "<u4", 4)]
    )  # fmt: skip
    table = np.zeros(count, dtype=record)
    table["id"] = np.arange(count, 0, -1)
    table["xyz"] = np.random.default_rng(1).normal(size=(count, 3))
    table["length"] = 2
    path = tmp_path / "points3D.bin"
    path.write_bytes(struct.pack("<Q", count) + table.tobytes())
    started = time.perf_counter()
    points = read_points3d_binary(path)
    seconds = time.perf_counter() - started
    np.testing.assert_array_equal(points.ids, np.arange(1, count + 1))
    np.testing.assert_array_equal(points.xyz, table["xyz"][::-1])
    assert seconds < 10.0, f"{seconds:.1f} s for 10^5 points"
