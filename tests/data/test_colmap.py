"""COLMAP sparse models as a dataset: the format both ways, the pose conversion, splits, errors.

Expected values are worked out by hand or packed with `struct` from the documented
layout here, independently of relocfw's reader and writer, so the two cannot share a
mistake unnoticed.
"""

import json
import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import quaternion_to_matrix
from relocfw.core.values import Pose
from relocfw.data.colmap import (
    UNITS_NOTE,
    ColmapDataset,
    colmap_to_pose,
    pose_to_colmap,
)
from relocfw.data.colmap_cameras import pinhole_of, why_not_pinhole
from relocfw.data.colmap_format import (
    CAMERA_MODELS,
    ColmapCamera,
    ColmapImage,
    read_cameras_binary,
    read_cameras_text,
    read_images_binary,
    read_images_text,
    write_model,
)
from tests.cli_runs import relocfw
from tests.conftest import TINY_MODEL

CAMERA = ColmapCamera(1, "PINHOLE", 48, 36, (40.0, 41.0, 24.0, 18.0))
NO_POINT = 2**64 - 1  # COLMAP's "no 3-D point" id, as uint64


def random_poses(count: int, seed: int = 0) -> list[Pose]:
    rng = np.random.default_rng(seed)
    quaternions = rng.normal(size=(count, 4))
    quaternions /= np.linalg.norm(quaternions, axis=1, keepdims=True)
    return [Pose(rng.uniform(-5, 5, 3), q) for q in quaternions]


def write_image(path: Path, seed: int = 0) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    assert cv2.imwrite(str(path), rng.integers(0, 256, (36, 48, 3), dtype=np.uint8))


def project(
    root: Path, poses: dict[str, Pose], binary: bool, model: str = "sparse/0"
) -> list[ColmapImage]:
    """A COLMAP project folder: images/NAME and a sparse model written by relocfw."""
    images = []
    for number, (name, pose) in enumerate(poses.items(), start=1):
        write_image(root / "images" / name, number)
        qvec, tvec = pose_to_colmap(pose)
        # Image ids out of order and not contiguous, as COLMAP's are.
        images.append(ColmapImage(100 - 3 * number, tuple(qvec), tuple(tvec), 1, name))
    write_model(root / model, [CAMERA], images, binary=binary)
    return images


def named_poses(names: list[str], seed: int = 0) -> dict[str, Pose]:
    return dict(zip(names, random_poses(len(names), seed), strict=True))


def same_rotation(q1, q2, tolerance=1e-9) -> bool:
    """q and -q are the same rotation."""
    q1, q2 = np.asarray(q1), np.asarray(q2)
    return np.allclose(q1, q2, atol=tolerance) or np.allclose(q1, -q2, atol=tolerance)


# ------------------------------------------------------------------ the conversion


def test_relocfw_to_colmap_to_relocfw_is_the_identity():
    for pose in random_poses(50):
        back = colmap_to_pose(*pose_to_colmap(pose))
        np.testing.assert_allclose(back.position, pose.position, atol=1e-9)
        np.testing.assert_allclose(back.quaternion, pose.quaternion, atol=1e-9)


def test_colmap_to_relocfw_to_colmap_is_the_identity_up_to_quaternion_sign():
    rng = np.random.default_rng(1)
    for _ in range(50):
        qvec = rng.normal(size=4)
        qvec /= np.linalg.norm(qvec)  # both signs of w occur
        tvec = rng.uniform(-5, 5, 3)
        back_q, back_t = pose_to_colmap(colmap_to_pose(qvec, tvec))
        assert back_q[0] >= 0
        assert same_rotation(back_q, qvec)
        np.testing.assert_allclose(back_t, tvec, atol=1e-9)


def test_colmap_pose_is_world_to_camera():
    """x_cam = R x_world + t: the camera centre maps to the camera origin."""
    rng = np.random.default_rng(2)
    qvec = rng.normal(size=4)
    qvec /= np.linalg.norm(qvec)
    tvec = rng.uniform(-5, 5, 3)
    pose = colmap_to_pose(qvec, tvec)
    world_to_camera = quaternion_to_matrix(qvec)
    np.testing.assert_allclose(world_to_camera @ pose.position + tvec, 0, atol=1e-12)
    camera_to_world = quaternion_to_matrix(pose.quaternion)
    np.testing.assert_allclose(camera_to_world, world_to_camera.T, atol=1e-12)


def test_hand_written_images_txt_gives_the_known_camera(tmp_path):
    # A camera at world (1, 2, 3) looking along world +X, image "down" along world -Z.
    # Camera-to-world columns (x right, y down, z forward): (0,-1,0), (0,0,-1), (1,0,0);
    # world-to-camera R is its transpose, t = -R C = (2, 3, -1), and R's quaternion
    # (trace 0: w = 1/2, x = (R21 - R12)/2 = 1/2, ...) is (0.5, 0.5, -0.5, 0.5).
    # The second camera sits at the origin-facing identity rotation, 4 units along +Z.
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    (tmp_path / "sparse" / "0" / "cameras.txt").write_text("1 SIMPLE_PINHOLE 48 36 40 24 18\n")
    (tmp_path / "sparse" / "0" / "images.txt").write_text(
        "# Image list with two lines of data per image:\n"
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
        "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
        "1 0.5 0.5 -0.5 0.5 2 3 -1 1 east.png\n"
        "10.5 20.25 -1 30 40 7\n"
        "2 1 0 0 0 0 0 -4 1 up.png\n"
        "\n"
    )
    write_image(tmp_path / "images" / "east.png")
    write_image(tmp_path / "images" / "up.png")
    dataset = ColmapDataset(str(tmp_path), train=["up.png"], test=["east.png"])
    (east,) = dataset.frames("test")
    np.testing.assert_allclose(east.pose.position, [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(east.pose.quaternion, [0.5, -0.5, 0.5, -0.5], atol=1e-12)
    rotation = quaternion_to_matrix(east.pose.quaternion)
    np.testing.assert_allclose(rotation @ [0, 0, 1], [1, 0, 0], atol=1e-12)  # forward
    np.testing.assert_allclose(rotation @ [0, 1, 0], [0, 0, -1], atol=1e-12)  # down
    (up,) = dataset.frames("train")
    np.testing.assert_allclose(up.pose.position, [0, 0, 4], atol=1e-12)
    np.testing.assert_allclose(up.pose.quaternion, [1, 0, 0, 0], atol=1e-12)
    assert east.name == "east.png" and east.image_path == tmp_path / "images" / "east.png"


# ------------------------------------------------------------------------ the format


@pytest.mark.parametrize("binary", [False, True], ids=["text", "binary"])
def test_written_model_reads_back_with_the_same_poses(tmp_path, binary):
    names = [f"seq{s}/frame-{i:03d}.png" for s in (1, 2) for i in range(4)]
    poses = named_poses(names)
    written = project(tmp_path, poses, binary)
    dataset = ColmapDataset(str(tmp_path), train=["seq1/*"], test=["seq2/*"])
    frames = dataset.frames("train") + dataset.frames("test")
    assert [f.name for f in frames] == names
    for frame in frames:
        np.testing.assert_allclose(frame.pose.position, poses[frame.name].position, atol=1e-9)
        np.testing.assert_allclose(frame.pose.quaternion, poses[frame.name].quaternion, atol=1e-9)
        assert frame.image_path == tmp_path / "images" / frame.name
    folder = tmp_path / "sparse" / "0"
    if binary:
        read, cameras = (
            read_images_binary(folder / "images.bin"),
            read_cameras_binary(folder / "cameras.bin"),
        )
    else:
        read, cameras = (
            read_images_text(folder / "images.txt"),
            read_cameras_text(folder / "cameras.txt"),
        )
    # Every field back exactly: ids, names, camera ids and the floats bit for bit.
    assert [(i.image_id, i.qvec, i.tvec, i.camera_id, i.name) for i in read] == [
        (i.image_id, i.qvec, i.tvec, i.camera_id, i.name) for i in written
    ]
    assert cameras == [CAMERA]


def test_binary_layout_matches_the_documentation(tmp_path):
    """An images.bin packed by hand, with 2-D points that the reader must pass over."""
    records = [
        (7, (0.5, 0.5, -0.5, 0.5), (2.0, 3.0, -1.0), 1, "a/east.png", [(1.5, 2.5, 9)]),
        (3, (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, -4.0), 2, "up.png", [(0, 0, NO_POINT)] * 3),
    ]
    data = struct.pack("<Q", len(records))
    for image_id, q, t, camera, name, points in records:
        data += struct.pack("<I", image_id) + struct.pack("<4d", *q) + struct.pack("<3d", *t)
        data += struct.pack("<I", camera) + name.encode() + b"\0"
        data += struct.pack("<Q", len(points))
        data += b"".join(struct.pack("<ddQ", *p) for p in points)
    (tmp_path / "images.bin").write_bytes(data)
    read = read_images_binary(tmp_path / "images.bin")
    assert [(i.image_id, i.qvec, i.tvec, i.camera_id, i.name) for i in read] == [
        r[:5] for r in records
    ]
    cameras = struct.pack("<Q", 2)
    cameras += struct.pack("<IiQQ", 1, 0, 640, 480) + struct.pack("<3d", 500, 320, 240)
    cameras += struct.pack("<IiQQ", 2, 4, 64, 48) + struct.pack("<8d", *range(1, 9))
    (tmp_path / "cameras.bin").write_bytes(cameras)
    assert read_cameras_binary(tmp_path / "cameras.bin") == [
        ColmapCamera(1, "SIMPLE_PINHOLE", 640, 480, (500.0, 320.0, 240.0)),
        ColmapCamera(2, "OPENCV", 64, 48, tuple(float(v) for v in range(1, 9))),
    ]


def test_binary_model_is_read_when_both_are_there(tmp_path):
    names = ["a.png", "b.png"]
    project(tmp_path, named_poses(names, seed=1), binary=False)
    binary_poses = named_poses(names, seed=2)
    project(tmp_path, binary_poses, binary=True)
    dataset = ColmapDataset(str(tmp_path), test=["b.png"])
    (frame,) = dataset.frames("train")
    np.testing.assert_allclose(frame.pose.position, binary_poses["a.png"].position, atol=1e-9)
    assert dataset.model_file.name == "images.bin"


def test_other_model_and_image_folders(tmp_path):
    poses = named_poses(["x.png", "y.png"])
    project(tmp_path, poses, binary=True, model="recon/sparse/1")
    (tmp_path / "images").rename(tmp_path / "frames")
    dataset = ColmapDataset(str(tmp_path), test=["y.png"], model="recon/sparse/1", images="frames")
    assert [f.image_path for f in dataset.frames("train")] == [tmp_path / "frames" / "x.png"]


def test_units_are_declared_not_metric(tmp_path):
    project(tmp_path, named_poses(["a.png", "b.png"]), binary=True)
    dataset = ColmapDataset(str(tmp_path), test=["b.png"])
    assert dataset.metric is False
    assert dataset.units_note == UNITS_NOTE
    assert "not metres" in UNITS_NOTE and "\n" not in UNITS_NOTE


# --------------------------------------------------------------------------- splits


@pytest.fixture
def sequences(tmp_path):
    """Three sequences of three images each, binary model."""
    names = [f"seq{s}/{i}.png" for s in (1, 2, 3) for i in range(3)]
    project(tmp_path, named_poses(names), binary=True)
    return tmp_path


def names_of(dataset, split):
    return [f.name for f in dataset.frames(split)]


def test_split_by_names(sequences):
    dataset = ColmapDataset(str(sequences), train=["seq1/0.png", "seq3/2.png"], test=["seq2/1.png"])
    assert names_of(dataset, "train") == ["seq1/0.png", "seq3/2.png"]
    assert names_of(dataset, "test") == ["seq2/1.png"]


def test_split_by_glob_patterns_and_the_rest(sequences):
    dataset = ColmapDataset(str(sequences), test=["seq2/*", "seq3/[01].png"])
    assert names_of(dataset, "test") == ["seq2/0.png", "seq2/1.png", "seq2/2.png"] + [
        "seq3/0.png",
        "seq3/1.png",
    ]
    # train not given: every registered image that is not a test image.
    assert names_of(dataset, "train") == ["seq1/0.png", "seq1/1.png", "seq1/2.png", "seq3/2.png"]
    only_train = ColmapDataset(str(sequences), train=["seq1/*", "seq2/*"])
    assert names_of(only_train, "test") == ["seq3/0.png", "seq3/1.png", "seq3/2.png"]


def test_split_by_list_files(sequences):
    (sequences / "train.txt").write_text("# map images\nseq1/*\n\n  seq2/0.png  \n")
    lists = sequences / "lists"
    lists.mkdir()
    (lists / "test.txt").write_text("seq3/1.png\n")
    dataset = ColmapDataset(str(sequences), train="train.txt", test=str(lists / "test.txt"))
    assert names_of(dataset, "train") == ["seq1/0.png", "seq1/1.png", "seq1/2.png", "seq2/0.png"]
    assert names_of(dataset, "test") == ["seq3/1.png"]


def test_an_image_in_both_splits_is_an_error(sequences):
    with pytest.raises(ConfigError, match=r"share 1 images \(seq1/2.png\)"):
        ColmapDataset(str(sequences), train=["seq1/*"], test=["seq1/2.png", "seq2/*"])


def test_a_name_that_matches_nothing_is_named_with_where_it_was_given(sequences):
    with pytest.raises(DataError, match=r"dataset.test: 'seq9/\*' matches no image registered"):
        ColmapDataset(str(sequences), test=["seq9/*"])
    (sequences / "test.txt").write_text("seq2/0.png\nseq2/typo.png\n")
    with pytest.raises(DataError) as error:
        ColmapDataset(str(sequences), test="test.txt")
    assert f"{sequences / 'test.txt'}:2: 'seq2/typo.png' matches no image" in str(error.value)
    # skip: left out and listed (e.g. an image COLMAP did not register).
    dataset = ColmapDataset(str(sequences), test="test.txt", on_error="skip")
    assert names_of(dataset, "test") == ["seq2/0.png"]
    assert len(dataset.on_error.skipped) == 1 and "seq2/typo.png" in dataset.on_error.skipped[0]


def test_bad_split_options(sequences):
    with pytest.raises(ConfigError, match="at least one split"):
        ColmapDataset(str(sequences))
    with pytest.raises(ConfigError, match="dataset.train must be a non-empty list"):
        ColmapDataset(str(sequences), train=[], test=["seq1/*"])
    with pytest.raises(DataError, match=r"dataset.test: list file not found: .*seq1/\*"):
        ColmapDataset(str(sequences), test="seq1/*")  # a string is a file; lists are lists
    with pytest.raises(ConfigError, match="dataset.root is not set"):
        ColmapDataset(None, test=["seq1/*"])


# --------------------------------------------------------------------------- errors


@pytest.fixture
def text_project(tmp_path):
    names = ["a.png", "b.png", "c.png"]
    project(tmp_path, named_poses(names), binary=False)
    return tmp_path, tmp_path / "sparse" / "0" / "images.txt"


def replace_image_line(path: Path, name: str, fields: dict[int, str]) -> int:
    """Change fields of the image line of `name`; returns its 1-based line number."""
    lines = path.read_text().splitlines()
    for index, line in enumerate(lines):
        if line.endswith(f" {name}"):
            values = line.split()
            for position, value in fields.items():
                values[position] = value
            lines[index] = " ".join(values)
            path.write_text("\n".join(lines) + "\n")
            return index + 1
    raise AssertionError(name)


def test_registered_image_missing_on_disk(text_project):
    root, images_txt = text_project
    (root / "images" / "b.png").unlink()
    line = replace_image_line(images_txt, "b.png", {})
    with pytest.raises(DataError) as error:
        ColmapDataset(str(root), test=["c.png"])
    assert f"{images_txt}:{line}: image 'b.png' not found: {root / 'images' / 'b.png'}" in str(
        error.value
    )
    skipping = ColmapDataset(str(root), test=["c.png"], on_error="skip")
    assert names_of(skipping, "train") == ["a.png"]
    assert "b.png" in skipping.on_error.skipped[0]


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({1: "0.9", 2: "0.3", 3: "0", 4: "0"}, "has norm 0.948683, not 1"),
        ({1: "0", 2: "0", 3: "0", 4: "0"}, "has norm 0, not 1"),
        ({3: "nan"}, "NaN or infinite value"),
        ({6: "inf"}, "NaN or infinite value"),
        ({5: "x"}, "not a number"),
        ({0: "1.5"}, "IMAGE_ID must be an integer"),
    ],
    ids=["non-unit", "zero", "nan", "infinite translation", "text", "id"],
)
def test_bad_pose_in_images_txt_names_the_line(text_project, fields, message):
    root, images_txt = text_project
    line = replace_image_line(images_txt, "b.png", fields)
    with pytest.raises(DataError) as error:
        ColmapDataset(str(root), test=["c.png"])
    assert f"{images_txt}:{line}: " in str(error.value) and message in str(error.value)


def test_bad_pose_in_images_bin_names_the_image(tmp_path):
    names = ["a.png", "b.png"]
    written = project(tmp_path, named_poses(names), binary=True)
    images_bin = tmp_path / "sparse" / "0" / "images.bin"
    data = bytearray(images_bin.read_bytes())
    # The second image's QX: 8 (count) + the first record (4 + 56 + 4 + name + 8) + 4 + 8.
    offset = 8 + (4 + 56 + 4 + len("a.png") + 1 + 8) + 4 + 8
    assert struct.unpack_from("<d", data, offset)[0] == written[1].qvec[1]
    struct.pack_into("<d", data, offset, float("nan"))
    images_bin.write_bytes(bytes(data))
    with pytest.raises(DataError) as error:
        ColmapDataset(str(tmp_path), test=["a.png"])
    assert f"{images_bin}: image 2 of 2 (IMAGE_ID {written[1].image_id}): pose must be" in str(
        error.value
    )
    struct.pack_into("<d", data, offset, 2.0)
    images_bin.write_bytes(bytes(data))
    with pytest.raises(DataError, match=r"image 2 of 2 .* not 1"):
        ColmapDataset(str(tmp_path), test=["a.png"])


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda data: data[:-5], "truncated or corrupt at byte"),
        (lambda data: data + b"\0\0\0", "3 bytes left after the last of the images"),
        (lambda data: struct.pack("<Q", 10**12) + data[8:], f"{10**12} images announced"),
        (lambda data: data[:-8] + struct.pack("<Q", 5), "the 2-D points of image 2 of 2"),
        (lambda data: data.replace(b"b.png\0", b"b.png!"), "truncated or corrupt at byte"),
        (lambda data: data.replace(b"b.png", b"b\xff\xfeng"), "is not UTF-8"),
        (lambda data: b"", "truncated or corrupt at byte 0 of 0"),
    ],
    ids=[
        "truncated",
        "trailing bytes",
        "huge count",
        "huge point count",
        "no NUL",
        "utf8",
        "empty",
    ],
)
def test_corrupt_images_bin_names_the_file(tmp_path, damage, message):
    project(tmp_path, named_poses(["a.png", "b.png"]), binary=True)
    images_bin = tmp_path / "sparse" / "0" / "images.bin"
    images_bin.write_bytes(damage(images_bin.read_bytes()))
    with pytest.raises(DataError) as error:
        ColmapDataset(str(tmp_path), test=["a.png"], on_error="skip")  # structural: always
    assert str(error.value).startswith(f"{images_bin}: ") and message in str(error.value)


def test_corrupt_cameras_bin_names_the_file(tmp_path):
    path = tmp_path / "cameras.bin"
    path.write_bytes(struct.pack("<Q", 1) + struct.pack("<IiQQ", 4, 99, 8, 8))
    with pytest.raises(DataError, match=r"CAMERA_ID 4\) has camera model id 99"):
        read_cameras_binary(path)
    path.write_bytes(struct.pack("<Q", 1) + struct.pack("<IiQQ", 4, 1, 8, 8) + b"\0" * 24)
    with pytest.raises(DataError, match=rf"{path}: truncated .*parameters of camera 1 of 1"):
        read_cameras_binary(path)


def test_missing_points2d_line_is_caught_not_swallowed(text_project):
    root, images_txt = text_project
    lines = [line for line in images_txt.read_text().splitlines() if line.strip()]
    images_txt.write_text("\n".join(lines) + "\n")  # every POINTS2D line dropped
    with pytest.raises(DataError, match=rf"{images_txt}:6: expected the POINTS2D line"):
        ColmapDataset(str(root), test=["c.png"])


def test_duplicate_names_and_ids(text_project):
    root, images_txt = text_project
    first = images_txt.read_text().splitlines()[4]
    line = replace_image_line(images_txt, "c.png", {0: first.split()[0]})
    with pytest.raises(DataError, match=rf"{images_txt}:{line}: duplicate IMAGE_ID"):
        ColmapDataset(str(root), test=["c.png"])


def test_missing_model_folder_and_files(tmp_path):
    project(tmp_path, named_poses(["a.png", "b.png"]), binary=True, model="sparse")
    with pytest.raises(DataError) as error:
        ColmapDataset(str(tmp_path), test=["a.png"])
    text = str(error.value)
    assert f"dataset.model: COLMAP model folder not found: {tmp_path / 'sparse' / '0'}" in text
    assert "(models found in" in text and ": sparse)" in text
    (tmp_path / "sparse" / "0").mkdir()
    with pytest.raises(DataError, match="not a COLMAP sparse model: no images.bin or images.txt"):
        ColmapDataset(str(tmp_path), test=["a.png"])
    with pytest.raises(DataError, match="dataset.root: folder not found"):
        ColmapDataset(str(tmp_path / "nowhere"), test=["a.png"])
    with pytest.raises(DataError, match="dataset.images: image folder not found"):
        ColmapDataset(str(tmp_path), test=["a.png"], model="sparse", images="pictures")


def test_skip_leaves_out_bad_lines_and_lists_them(text_project):
    root, images_txt = text_project
    line = replace_image_line(images_txt, "a.png", {2: "nan"})
    dataset = ColmapDataset(str(root), test=["c.png"], on_error="skip")
    assert names_of(dataset, "train") == ["b.png"]
    assert dataset.on_error.skipped[0].startswith(f"{images_txt}:{line}: ")


# -------------------------------------------------------------------------- cameras

CAMERAS_HEADER = "# Camera list with one line of data per camera:\n# Number of cameras: 2\n"


def write_cameras_txt(root: Path, *lines: str) -> Path:
    """cameras.txt of the text project: a two-line header, then `lines` from line 3 on."""
    path = root / "sparse" / "0" / "cameras.txt"
    path.write_text(CAMERAS_HEADER + "".join(f"{line}\n" for line in lines))
    return path


def test_the_binary_model_ids_are_colmaps():
    # COLMAP's CameraModelId order (src/colmap/sensor/models.h): cameras.bin stores it.
    assert [CAMERA_MODELS[i] for i in range(11)] == [
        ("SIMPLE_PINHOLE", 3),
        ("PINHOLE", 4),
        ("SIMPLE_RADIAL", 4),
        ("RADIAL", 5),
        ("OPENCV", 8),
        ("OPENCV_FISHEYE", 8),
        ("FULL_OPENCV", 12),
        ("FOV", 5),
        ("SIMPLE_RADIAL_FISHEYE", 4),
        ("RADIAL_FISHEYE", 5),
        ("THIN_PRISM_FISHEYE", 12),
    ]


def test_cameras_txt_is_read_and_kept_beside_the_frames(text_project):
    root, _ = text_project
    write_cameras_txt(
        root,
        "1 PINHOLE 48 36 40.5 41.25 24 18",
        "",
        "7 OPENCV 640 480 500 501 320 240 -0.1 0.01 0.001 -0.002",
    )
    dataset = ColmapDataset(str(root), test=["c.png"])
    assert dataset.cameras == {
        1: ColmapCamera(1, "PINHOLE", 48, 36, (40.5, 41.25, 24.0, 18.0)),
        7: ColmapCamera(7, "OPENCV", 640, 480, (500, 501, 320, 240, -0.1, 0.01, 0.001, -0.002)),
    }
    (frame,) = dataset.frames("test")
    assert dataset.camera(frame.name) is dataset.cameras[1]  # every image uses camera 1
    assert dataset.cameras[1].source == f"{root / 'sparse' / '0' / 'cameras.txt'}:3"
    assert type(frame).__name__ == "Frame" and frame.name == "c.png"  # frames as before
    with pytest.raises(DataError, match="'x.png' is not an image registered in"):
        dataset.camera("x.png")


def test_a_binary_models_cameras_are_kept(tmp_path):
    project(tmp_path, named_poses(["a.png", "b.png"]), binary=True)
    dataset = ColmapDataset(str(tmp_path), test=["b.png"])
    assert dataset.cameras == {1: CAMERA} and dataset.camera("a.png") == CAMERA
    assert dataset.cameras_file == tmp_path / "sparse" / "0" / "cameras.bin"


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("1 PINHOLEX 48 36 40 41 24 18", "unknown COLMAP camera model 'PINHOLEX' (known: "),
        ("1 PINHOLE 48 36 40 41 24", "camera model PINHOLE takes 4 parameters, got 3"),
        ("1 SIMPLE_RADIAL 48 36 40 24 18", "camera model SIMPLE_RADIAL takes 4 parameters"),
        ("1 PINHOLE 0 36 40 41 24 18", "camera size must be positive, got WIDTH 0 HEIGHT 36"),
        ("1 PINHOLE 48 -36 40 41 24 18", "camera size must be positive"),
        ("1 PINHOLE 48 36 40 0 24 18", "the focal length of a PINHOLE camera must be positive"),
        ("1 SIMPLE_PINHOLE 48 36 -40 24 18", "focal length of a SIMPLE_PINHOLE camera"),
        ("1 PINHOLE 48 36 nan 41 24 18", "PARAMS: NaN or infinite value"),
        ("1 PINHOLE 48.5 36 40 41 24 18", "WIDTH must be an integer, got '48.5'"),
        ("1 PINHOLE 48", "expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]'"),
    ],
    ids=[
        "unknown model",
        "too few parameters",
        "too few for simple radial",
        "zero width",
        "negative height",
        "zero fy",
        "negative f",
        "nan",
        "fractional width",
        "short line",
    ],
)
def test_a_bad_camera_line_names_the_file_and_line(text_project, line, message):
    root, _ = text_project
    cameras_txt = write_cameras_txt(root, line)
    with pytest.raises(DataError) as error:
        ColmapDataset(str(root), test=["c.png"])
    assert str(error.value).startswith(f"{cameras_txt}:3: ") and message in str(error.value)
    assert "\n" not in str(error.value)


def test_an_image_whose_camera_is_missing_names_the_image_line(text_project):
    root, images_txt = text_project
    cameras_txt = write_cameras_txt(root, "1 PINHOLE 48 36 40 41 24 18")
    line = replace_image_line(images_txt, "b.png", {8: "9"})
    with pytest.raises(DataError) as error:
        ColmapDataset(str(root), test=["c.png"])
    assert str(error.value) == (
        f"{images_txt}:{line}: image 'b.png' has CAMERA_ID 9, which {cameras_txt} does not hold"
    )
    # skip: the image is left out and listed, like any other bad entry.
    skipping = ColmapDataset(str(root), test=["c.png"], on_error="skip")
    assert names_of(skipping, "train") == ["a.png"]
    assert "CAMERA_ID 9" in skipping.on_error.skipped[0]


def test_a_skipped_camera_takes_its_images_with_it(text_project):
    root, images_txt = text_project
    write_cameras_txt(root, "1 NOSUCH 48 36 40 41 24 18", "2 PINHOLE 48 36 40 41 24 18")
    replace_image_line(images_txt, "b.png", {8: "2"})  # a.png and c.png stay on camera 1
    dataset = ColmapDataset(str(root), test=["b.png"], on_error="skip")
    assert dataset.cameras.keys() == {2} and names_of(dataset, "test") == ["b.png"]
    assert names_of(dataset, "train") == []
    first, *images = dataset.on_error.skipped
    assert "unknown COLMAP camera model 'NOSUCH'" in first
    assert [("'a.png' has CAMERA_ID 1" in m, "'c.png' has CAMERA_ID 1" in m) for m in images] == [
        (True, False),
        (False, True),
    ]


def test_duplicate_camera_ids_and_a_missing_cameras_file(text_project):
    root, _ = text_project
    cameras_txt = write_cameras_txt(
        root, "1 PINHOLE 48 36 40 41 24 18", "1 SIMPLE_PINHOLE 48 36 40 24 18"
    )
    with pytest.raises(DataError, match=rf"{cameras_txt}:4: duplicate CAMERA_ID 1 \(first at "):
        ColmapDataset(str(root), test=["c.png"])
    cameras_txt.unlink()
    with pytest.raises(DataError, match=r"no cameras.txt beside images.txt"):
        ColmapDataset(str(root), test=["c.png"])


def test_a_binary_camera_with_impossible_values_names_the_camera(tmp_path):
    project(tmp_path, named_poses(["a.png", "b.png"]), binary=True)
    cameras_bin = tmp_path / "sparse" / "0" / "cameras.bin"
    data = struct.pack("<Q", 1) + struct.pack("<IiQQ", 1, 1, 48, 36)
    cameras_bin.write_bytes(data + struct.pack("<4d", 0, 41, 24, 18))  # fx = 0
    with pytest.raises(DataError) as error:
        ColmapDataset(str(tmp_path), test=["a.png"])
    assert str(error.value).startswith(f"{cameras_bin}: camera 1 of 1 (CAMERA_ID 1): the focal")
    cameras_bin.write_bytes(data + struct.pack("<4d", 40, 41, float("inf"), 18))
    with pytest.raises(DataError, match=r"camera 1 of 1 \(CAMERA_ID 1\): NaN or infinite"):
        ColmapDataset(str(tmp_path), test=["a.png"])
    cameras_bin.write_bytes(
        struct.pack("<Q", 1) + struct.pack("<IiQQ", 5, 1, 48, 36) + struct.pack("<4d", 1, 1, 1, 1)
    )
    with pytest.raises(DataError, match=r"images.bin: image .* has CAMERA_ID 1, which .* does not"):
        ColmapDataset(str(tmp_path), test=["a.png"])


# ---------------------------------------------------------------------------- the CLI


def test_cli_composes_the_colmap_dataset(tmp_path):
    result = relocfw(
        ["dataset=colmap", f"dataset.root={tmp_path}", "dataset.test=[seq3/*]", "--cfg", "job"],
        tmp_path,
    )
    assert result.returncode == 0, result.stderr
    assert "_target_: relocfw.data.colmap.ColmapDataset" in result.stdout
    assert f"root: {tmp_path}" in result.stdout and "model: sparse/0" in result.stdout


def test_cli_relocalizes_a_colmap_project(tmp_path):
    names = [f"seq{s}/{i:02d}.png" for s in (1, 2) for i in range(8)] + [
        f"seq3/{i:02d}.png" for i in range(4)
    ]
    project(tmp_path / "project", named_poses(names), binary=True)
    run_dir = tmp_path / "run"
    result = relocfw(
        [
            *TINY_MODEL,
            "dataset=colmap",
            f"dataset.root={tmp_path / 'project'}",
            "dataset.test=[seq3/*]",
            f"hydra.run.dir={run_dir}",
        ],
        tmp_path,
    )
    assert result.returncode == 0, result.stderr
    rows = (run_dir / "results.csv").read_text().splitlines()
    assert len(rows) == 1 + 3 * 4 and all("seq3/" in row for row in rows[1:])
    # A COLMAP model has no scale of its own: every report says so.
    assert UNITS_NOTE in result.stdout
    assert (run_dir / "table.txt").read_text().startswith(f"Note: {UNITS_NOTE}.")
    summary = json.loads((run_dir / "summary.json").read_text())
    assert all(row["units_note"] == UNITS_NOTE for row in summary)

    (tmp_path / "project" / "images" / "seq1" / "03.png").unlink()
    broken = relocfw(
        [
            *TINY_MODEL,
            "dataset=colmap",
            f"dataset.root={tmp_path / 'project'}",
            "dataset.test=[seq3/*]",
        ],
        tmp_path,
    )
    assert broken.returncode == 2
    assert "image 'seq1/03.png' not found" in broken.stderr and "images.bin: image" in broken.stderr


# ------------------------------------------------------- cameras as pinholes


@pytest.mark.parametrize(
    ("model", "params", "expected"),
    [
        # COLMAP's principal point is from the image corner; relocfw's from the
        # top-left pixel's centre, half a pixel in.
        ("PINHOLE", (40.5, 41.25, 24.0, 18.0), (40.5, 41.25, 23.5, 17.5)),
        ("SIMPLE_PINHOLE", (40.0, 24.5, 18.0), (40.0, 40.0, 24.0, 17.5)),
        ("SIMPLE_RADIAL", (40.0, 24.0, 18.0, 0.0), (40.0, 40.0, 23.5, 17.5)),
        ("OPENCV", (40.0, 41.0, 24.0, 18.0, 0, 0, 0, 0), (40.0, 41.0, 23.5, 17.5)),
    ],
)
def test_a_camera_without_distortion_is_a_pinhole(model, params, expected):
    camera = pinhole_of(ColmapCamera(3, model, 48, 36, params))
    assert camera == PinholeCamera(*expected, 48, 36)
    assert why_not_pinhole(ColmapCamera(3, model, 48, 36, params)) == ""


@pytest.mark.parametrize(
    ("model", "params", "reason"),
    [
        (
            "SIMPLE_RADIAL",
            (40.0, 24.0, 18.0, -0.1),
            "camera 3 is SIMPLE_RADIAL with lens distortion (-0.1)",
        ),
        (
            "RADIAL",
            (40.0, 24.0, 18.0, 0.0, 0.02),
            "camera 3 is RADIAL with lens distortion (0 0.02)",
        ),
        (
            "OPENCV",
            (500, 501, 320, 240, -0.1, 0.01, 0.001, -0.002),
            "camera 3 is OPENCV with lens distortion (-0.1 0.01 0.001 -0.002)",
        ),
        # A fisheye projection is not x / z even with zero coefficients.
        (
            "OPENCV_FISHEYE",
            (40, 41, 24, 18, 0, 0, 0, 0),
            "camera 3 is OPENCV_FISHEYE, not a pinhole",
        ),
    ],
)
def test_a_camera_with_distortion_has_none_and_says_why(model, params, reason):
    camera = ColmapCamera(3, model, 48, 36, params)
    assert pinhole_of(camera) is None
    assert why_not_pinhole(camera).startswith(reason) and "\n" not in why_not_pinhole(camera)


def test_frames_carry_their_pinhole_camera_and_no_depth(text_project):
    root, _ = text_project
    write_cameras_txt(root, "1 SIMPLE_PINHOLE 48 36 40 24 18")
    dataset = ColmapDataset(str(root), test=["c.png"])
    frames = dataset.frames("train") + dataset.frames("test")
    assert {f.camera for f in frames} == {PinholeCamera(40, 40, 23.5, 17.5, 48, 36)}
    assert all(f.depth_path is None for f in frames)
    assert dataset.why_no_camera("a.png") == ""


def test_frames_of_a_distorted_camera_have_none_and_the_reason(text_project):
    root, _ = text_project
    write_cameras_txt(root, "1 OPENCV 48 36 40 41 24 18 -0.1 0.01 0 0")
    dataset = ColmapDataset(str(root), test=["c.png"])
    (frame,) = dataset.frames("test")
    assert frame.camera is None
    reason = dataset.why_no_camera(frame.name)
    assert reason == "camera 1 is OPENCV with lens distortion (-0.1 0.01 0 0)"
