"""The compact, memory-mapped structure map: round trips, queries, damaged files."""

from __future__ import annotations

import json

import numpy as np
import pytest

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import orientation_error_deg
from relocfw.structure.compact_map import CompactMap, localize_in_compact_map
from relocfw.structure.compact_writer import CompactMapWriter, camera_frame, save_compact_map
from relocfw.structure.descriptor_codes import (
    DescriptorCodec,
    grid_codec,
    train_product_quantiser,
)
from relocfw.structure.query_solver import localize_against
from relocfw.structure.structure_map import on_descriptor_grid


def with_points(structure, index):
    """Image `index`'s rows that have a 3-D point (what the compact map keeps)."""
    return np.isfinite(structure.points[index]).all(axis=1)


@pytest.fixture(scope="module")
def stored_descriptors(depth_structure):
    return np.concatenate(list(f.descriptors for f in depth_structure.features))


def test_grid_and_float32_round_trip_keep_every_point(depth_structure, tmp_path):
    save_compact_map(depth_structure, tmp_path / "map", None, "float32")
    compact = CompactMap.open(tmp_path / "map")
    assert len(compact) == len(depth_structure)
    assert compact.source == depth_structure.source
    assert isinstance(compact.codes, np.memmap) and isinstance(compact.points, np.memmap)
    for index in range(len(depth_structure)):
        rows = with_points(depth_structure, index)
        assert rows.sum() > 100
        features = compact.features(index)
        # The grid is the map's own: descriptors come back bit for bit.
        assert np.array_equal(
            features.descriptors, depth_structure.features[index].descriptors[rows]
        )
        # Keypoints are the points projected back: lifted from depth, on their rays.
        original = depth_structure.features[index].keypoints[rows]
        assert np.abs(features.keypoints - original).max() < 1e-3
        assert (
            np.abs(compact.world_points(index) - depth_structure.points[index][rows]).max() < 1e-5
        )
        assert compact.name(index) == depth_structure.names[index]
        assert compact.camera(index) == depth_structure.cameras[index]
        pose = compact.pose(index)
        assert np.array_equal(pose.position, depth_structure.poses[index].position)
        assert np.array_equal(pose.quaternion, depth_structure.poses[index].quaternion)


def test_pq_and_float16_keep_points_to_a_millimetre(depth_structure, stored_descriptors, tmp_path):
    codec = train_product_quantiser(stored_descriptors, 16)
    save_compact_map(depth_structure, tmp_path / "map", codec, "float16")
    compact = CompactMap.open(tmp_path / "map")
    assert compact.codes.shape[1] == 16 and compact.points.dtype == np.float16
    rows = with_points(depth_structure, 1)
    descriptors = depth_structure.features[1].descriptors[rows]
    assert np.array_equal(compact.features(1).descriptors, codec.decode(codec.encode(descriptors)))
    assert np.abs(compact.world_points(1) - depth_structure.points[1][rows]).max() < 3e-3
    # 16 code bytes and 6 point bytes a row, beside the small arrays and the centres.
    assert compact.codes.nbytes + compact.points.nbytes == 22 * len(compact.codes)


def test_a_query_gets_the_answer_of_the_map_in_memory(synthetic_scene, depth_structure, tmp_path):
    save_compact_map(depth_structure, tmp_path / "map")
    compact = CompactMap.open(tmp_path / "map")
    image, camera = synthetic_scene.query_image, synthetic_scene.camera
    in_memory = localize_against(depth_structure, image, camera, [0, 1])
    # Repeats are dropped, as localize_against drops them.
    answer = localize_in_compact_map(compact, image, camera, [0, 1, 0])
    assert answer.success and answer.inliers >= 200
    truth = synthetic_scene.query_pose
    assert np.linalg.norm(answer.pose.position - truth.position) < 0.01
    assert orientation_error_deg(answer.pose.quaternion, truth.quaternion) < 0.5
    assert abs(answer.inliers - in_memory.inliers) < 0.1 * in_memory.inliers


def test_a_keyframe_map_holds_the_chosen_images_in_order(depth_structure, tmp_path):
    save_compact_map(depth_structure, tmp_path / "map")
    compact = CompactMap.open(tmp_path / "map")
    small = compact.keyframe_map([1, 0])
    assert small.names == (depth_structure.names[1], depth_structure.names[0])
    assert len(small.features[0]) == int(with_points(depth_structure, 1).sum())
    assert np.isfinite(small.points[0]).all()
    with pytest.raises(DataError, match="image 2 is not in the map"):
        compact.keyframe_map([2])
    with pytest.raises(DataError, match="image -1 is not in the map"):
        compact.pose(-1)


def test_the_grid_codec_is_the_builders_grid(depth_structure):
    features = depth_structure.features[0]
    codec = grid_codec()
    assert codec.code_bytes == 128 and codec.kind == "grid"
    decoded = codec.decode(codec.encode(features.descriptors))
    assert np.array_equal(decoded, on_descriptor_grid(features).descriptors)


def test_product_quantiser_settings_are_checked(stored_descriptors):
    with pytest.raises(ConfigError, match="code_bytes must divide 128"):
        train_product_quantiser(stored_descriptors, 12)
    with pytest.raises(DataError, match="at least 256 training descriptors"):
        train_product_quantiser(stored_descriptors[:100], 16)
    with pytest.raises(DataError, match="centres must be float32"):
        DescriptorCodec(np.zeros((16, 256, 4), np.float64))


def damaged(folder, name):
    return folder / f"{name}.npy"


@pytest.fixture
def saved(depth_structure, tmp_path):
    folder = tmp_path / "map"
    save_compact_map(depth_structure, folder)
    return folder


def test_a_truncated_array_is_one_error_naming_it(saved):
    path = damaged(saved, "codes")
    path.write_bytes(path.read_bytes()[:-1000])
    with pytest.raises(DataError, match=r"codes\.npy is .* bytes, map\.json records"):
        CompactMap.open(saved)


def test_a_missing_or_corrupt_description_is_one_error_naming_it(saved):
    meta = saved / "map.json"
    text = meta.read_text()
    meta.write_text(text[: len(text) // 2])
    with pytest.raises(DataError, match=r"map\.json \(truncated or corrupt"):
        CompactMap.open(saved)
    meta.unlink()
    with pytest.raises(DataError, match=r"map\.json is missing"):
        CompactMap.open(saved)


def test_an_array_of_another_shape_is_one_error_naming_it(saved):
    np.save(saved / "poses.npy", np.zeros((5, 7)))
    meta = json.loads((saved / "map.json").read_text())
    meta["file_bytes"]["poses.npy"] = (saved / "poses.npy").stat().st_size
    (saved / "map.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match=r"poses\.npy holds float64 \[5, 7\]"):
        CompactMap.open(saved)


def test_a_corrupt_header_is_one_error_naming_it(saved):
    path = damaged(saved, "points")
    data = bytearray(path.read_bytes())
    data[:6] = b"nonnpy"
    path.write_bytes(bytes(data))
    with pytest.raises(DataError, match=r"points\.npy \(corrupt"):
        CompactMap.open(saved)


def test_damaged_points_are_named_when_their_image_is_read(saved):
    points = np.load(damaged(saved, "points"), mmap_mode="r+")
    points[0] = np.nan
    points.flush()
    del points
    compact = CompactMap.open(saved)
    compact.features(1)  # image 1 is intact
    with pytest.raises(DataError, match=r"points\.npy: image 0 has points that are not finite"):
        compact.keyframe_map([0])


def test_offsets_that_do_not_rise_are_refused(saved):
    offsets = np.load(damaged(saved, "offsets"), mmap_mode="r+")
    offsets[1] = offsets[2] + 1
    offsets.flush()
    del offsets
    with pytest.raises(DataError, match=r"offsets\.npy: offsets must rise"):
        CompactMap.open(saved)


def test_a_failed_write_leaves_nothing_and_the_old_map_stays(depth_structure, saved):
    before = sorted(p.name for p in saved.parent.iterdir())
    codec = grid_codec()
    with (
        pytest.raises(DataError, match="image 'wrong': codes must be uint8"),
        CompactMapWriter(saved, [3], codec) as writer,
    ):
        writer.add(np.zeros((2, 128), np.uint8), np.ones((2, 3)), None, None, "wrong")
    assert sorted(p.name for p in saved.parent.iterdir()) == before
    assert len(CompactMap.open(saved)) == len(depth_structure)


def test_a_point_beyond_float16_is_named(depth_structure, tmp_path):
    pose, camera = depth_structure.poses[0], depth_structure.cameras[0]
    far = np.array([[0.0, 0.0, 1e6]])
    with (
        pytest.raises(DataError, match="image 'far': a point is not finite"),
        CompactMapWriter(tmp_path / "map", [1], grid_codec()) as writer,
    ):
        writer.add(np.zeros((1, 128), np.uint8), far, pose, camera, "far")
    assert not (tmp_path / "map").exists()


def test_a_point_just_in_front_stays_in_front_in_float16(depth_structure, tmp_path):
    # z = 1e-9 rounds to 0 in float16; it is kept at float16's smallest z in front.
    pose, camera = depth_structure.poses[0], depth_structure.cameras[0]
    near = np.array([[0.5, -0.25, 1e-9], [0.0, 0.0, 2.0]])
    with CompactMapWriter(tmp_path / "map", [2], grid_codec()) as writer:
        writer.add(np.zeros((2, 128), np.uint8), near, pose, camera, "near")
    stored = CompactMap.open(tmp_path / "map").points
    smallest = np.finfo(np.float16).smallest_subnormal
    assert stored[0].tolist() == [0.5, -0.25, smallest] and stored[1].tolist() == [0, 0, 2]
    behind = np.array([[0.0, 0.0, -1e-9]])  # behind stays refused
    with (
        pytest.raises(DataError, match="image 'behind': a point is not finite"),
        CompactMapWriter(tmp_path / "other", [1], grid_codec()) as writer,
    ):
        writer.add(np.zeros((1, 128), np.uint8), behind, pose, camera, "behind")


def test_a_folder_that_is_not_a_map_is_never_replaced(tmp_path):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    with pytest.raises(ConfigError, match="exists and is not a compact structure map"):
        CompactMapWriter(tmp_path / "mine", [1], grid_codec())
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep"


def test_saving_again_replaces_the_map(depth_structure, saved):
    save_compact_map(depth_structure, saved, None, "float32")
    assert CompactMap.open(saved).points.dtype == np.float32
    # The map is a link to its one current version; nothing else but its lock is left.
    beside = sorted(p.name for p in saved.parent.iterdir())
    assert beside == sorted(["map", saved.resolve().name, ".map.lock"])


def test_camera_frame_points_lie_in_front(depth_structure):
    rows = with_points(depth_structure, 0)
    points = camera_frame(depth_structure.points[0][rows], depth_structure.poses[0])
    assert (points[:, 2] > 0).all()


def test_the_size_on_disk_is_the_opened_versions_while_another_is_published(depth_structure, saved):
    compact = CompactMap.open(saved)
    before = compact.file_bytes()
    assert before == sum(p.stat().st_size for p in saved.iterdir())
    save_compact_map(depth_structure, saved, None, "float32")  # removes the opened version
    assert compact.file_bytes() == before
    assert CompactMap.open(saved).file_bytes() > before  # float32 points
