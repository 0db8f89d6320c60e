"""dataset.pgt: 7-Scenes poses and colour cameras from a pseudo-ground-truth file in
Brachmann et al.'s format (rgb_file qw qx qy qz tx ty tz f, world-to-camera)."""

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.geometry import orientation_error_deg, pose_to_matrix, quaternion_to_matrix
from relocfw.core.sensor_poses import colour_pose
from relocfw.core.values import Pose
from relocfw.data import pseudo_ground_truth
from relocfw.data.colmap import pose_to_colmap
from relocfw.data.pseudo_ground_truth import read_pseudo_ground_truth
from relocfw.data.sevenscenes import SevenScenes, load_sevenscenes
from tests.cli_runs import relocfw_here
from tests.conftest import TINY_MODEL

REDKITCHEN = Path(__file__).resolve().parents[3] / "shared" / "data" / "7scenes-redkitchen"
SFM = REDKITCHEN / "pgt" / "redkitchen_sfm.txt"
DSLAM = REDKITCHEN / "pgt" / "redkitchen_dslam.txt"
ALL_SEQUENCES = [1, 2, 3, 4, 5, 6, 7]


@pytest.fixture
def redkitchen() -> Path:
    if not SFM.is_file() or not (REDKITCHEN / "redkitchen" / "TrainSplit.txt").is_file():
        pytest.skip(f"Red Kitchen frames or their pgt/ files not found at {REDKITCHEN}")
    return REDKITCHEN


def pgt_line(name: str, pose, focal: float) -> str:
    qvec, tvec = pose_to_colmap(pose)
    return " ".join([name, *(f"{v:.17g}" for v in (*qvec, *tvec, focal))])


def write_pgt(scene: Path, path: Path, extension: str = ".png", leave_out=(), focal=30.0):
    """A pgt file of a 7-Scenes-layout scene's own .pose.txt poses, its names ending in
    `extension`, without the frames in `leave_out`; the frames' poses by name."""
    frames = load_sevenscenes(scene, None, "train", sequences=[1, 2, 3])
    lines = [
        pgt_line(f"{frame.name}.color{extension}", frame.pose, focal)
        for frame in frames
        if frame.name not in leave_out
    ]
    path.write_text("\n".join(lines) + "\n")
    return {frame.name: frame.pose for frame in frames}


def test_the_sfm_file_gives_every_frame_its_pose_and_colour_camera(redkitchen):
    scenes = SevenScenes(str(redkitchen), "redkitchen", pgt=str(SFM))
    frames = scenes.frames("train") + scenes.frames("test")
    assert len(frames) == 700
    first = next(f for f in frames if f.name == "seq-02/frame-000000")
    # The file's line, converted by hand: camera centre -R(q)^T t, rotation R(q)^T.
    line = next(line for line in SFM.read_text().splitlines() if line.startswith("seq-02/"))
    values = np.array(line.split()[1:], dtype=np.float64)
    world_to_camera = quaternion_to_matrix(values[:4] / np.linalg.norm(values[:4]))
    np.testing.assert_allclose(first.pose.position, -world_to_camera.T @ values[4:7], atol=1e-9)
    np.testing.assert_allclose(pose_to_matrix(first.pose)[:3, :3], world_to_camera.T, atol=1e-9)
    camera = first.camera
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (values[7], values[7], 320.0, 240.0)
    assert (camera.width, camera.height) == (640, 480)
    # Depth is still the Kinect's raw depth, registered with its own camera.
    assert first.depth_path is not None and first.depth_camera.fx == 585.0
    assert first.depth_to_colour is not None and first.pose_to_colour is None


def test_the_published_dslam_file_is_relocfws_depth_sensor_conversion(redkitchen):
    """The DSLAM file's colour poses are `.pose.txt` moved by relocfw's depth-to-colour
    calibration (poses_of=depth) to a tenth of a millimetre, and 2.6 cm from the
    `.pose.txt` poses taken as the colour camera's (poses_of=colour, the default)."""
    published = {
        f.name: f.pose
        for f in load_sevenscenes(
            redkitchen,
            "redkitchen",
            "train",
            sequences=ALL_SEQUENCES,
            reference=read_pseudo_ground_truth(DSLAM),
        )
    }
    as_depth = load_sevenscenes(
        redkitchen, "redkitchen", "train", sequences=ALL_SEQUENCES, poses_of="depth"
    )
    assert len(published) == len(as_depth) == 700
    converted = [colour_pose(f.pose, f.pose_to_colour) for f in as_depth]
    truth = [published[f.name] for f in as_depth]
    positions = np.array([c.position for c in converted]) - [t.position for t in truth]
    assert np.linalg.norm(positions, axis=1).max() < 5e-4
    angles = orientation_error_deg(
        np.array([c.quaternion for c in converted]), np.array([t.quaternion for t in truth])
    )
    assert angles.max() < 0.01
    as_colour = np.array([f.pose.position for f in as_depth]) - [t.position for t in truth]
    assert np.median(np.linalg.norm(as_colour, axis=1)) == pytest.approx(0.0256, abs=5e-4)


def test_lines_match_frames_by_number_whatever_the_extension(tiny_scene, tmp_path, capsys):
    path = tmp_path / "pgt.txt"
    left_out = ("seq-01/frame-000002", "seq-03/frame-000001")
    truth = write_pgt(tiny_scene, path, extension=".jpg", leave_out=left_out, focal=31.5)
    frames = load_sevenscenes(
        tiny_scene, None, "train", sequences=[1, 2, 3], reference=read_pseudo_ground_truth(path)
    )
    assert len(frames) == len(truth) - 2
    assert not {f.name for f in frames} & set(left_out)
    for frame in frames:
        np.testing.assert_allclose(frame.pose.position, truth[frame.name].position, atol=1e-9)
        assert frame.camera.fx == 31.5 and frame.camera.cx == frame.camera.width / 2
    note = capsys.readouterr().err
    assert note.count("note:") == 1
    assert f"{path} (dataset.pgt) has no line for 2 frame(s)" in note
    assert all(name in note for name in left_out)


@pytest.mark.parametrize(
    "line, message",
    [
        ("seq-01/frame-000000.color.png 1 0 0 0 0 0 0", "expected 9 fields"),
        ("seq-01/frame-000000.color.png 1 0 0 0 0 nan 0 525", "NaN or infinite value"),
        ("seq-01/frame-000000.color.png 1 0 0 0 0 x 0 525", "not a number"),
        ("seq-01/frame-000000.color.png 2 0 0 0 0 0 0 525", "has norm 2, not 1"),
        ("seq-01/frame-000000.color.png 1 0 0 0 0 0 0 -525", "f must be a positive number"),
        ("kitchen/image_000.png 1 0 0 0 0 0 0 525", "names no sequence and frame"),
        ("seq-1/frame-0.color.jpg 1 0 0 0 0 0 0 525", "is sequence 1 frame 0 again"),
    ],
)
def test_a_bad_line_is_named_by_file_and_line(tmp_path, line, message):
    path = tmp_path / "pgt.txt"
    path.write_text(f"seq-01/frame-000000.color.png 1 0 0 0 0 0 0 525\n{line}\n")
    with pytest.raises(DataError, match=message) as error:
        read_pseudo_ground_truth(path)
    assert f"{path}:2:" in str(error.value)


def test_an_empty_missing_or_oversized_file_is_refused(tmp_path, monkeypatch):
    empty = tmp_path / "empty.txt"
    empty.write_text("# nothing\n")
    with pytest.raises(DataError, match=f"{empty}: holds no pose lines"):
        read_pseudo_ground_truth(empty)
    with pytest.raises(DataError, match="file not found"):
        read_pseudo_ground_truth(tmp_path / "absent.txt")
    monkeypatch.setattr(pseudo_ground_truth, "MAX_FILE_BYTES", 8)
    empty.write_text("seq-01/frame-000000.color.png 1 0 0 0 0 0 0 525\n")
    with pytest.raises(DataError, match="not a pseudo-ground-truth file"):
        read_pseudo_ground_truth(empty)


@pytest.mark.parametrize(
    "option, named",
    [
        ({"poses_of": "depth"}, "dataset.poses_of=depth"),
        ({"colour_focal": 530.0}, "dataset.colour_focal=530.0"),
        ({"intrinsics_for": "colour"}, "dataset.intrinsics_for=colour"),
    ],
)
def test_options_the_file_replaces_are_refused_beside_it(tiny_scene, tmp_path, option, named):
    path = tmp_path / "pgt.txt"
    write_pgt(tiny_scene, path)
    with pytest.raises(ConfigError, match=f"dataset.pgt={path} does not go with {named}"):
        SevenScenes(str(tiny_scene), None, pgt=str(path), **option)


def test_the_command_maps_and_scores_against_the_file(tiny_scene, tmp_path):
    """The same scene with its poses moved 2 m in a pgt file: the run's map and truth
    are the file's (the mean training pose moved with them)."""
    scene = tmp_path / "room"
    shutil.copytree(tiny_scene, scene)
    frames = load_sevenscenes(scene, None, "train", sequences=[1, 2, 3])
    moved = [
        pgt_line(f"{f.name}.color.png", Pose(f.pose.position + [2.0, 0, 0], f.pose.quaternion), 30)
        for f in frames
    ]
    (tmp_path / "pgt.txt").write_text("\n".join(moved) + "\n")
    common = ["dataset=sevenscenes", f"dataset.root={scene}", "dataset.scene=null", *TINY_MODEL]
    runs = {}
    for name, extra in (("own", []), ("pgt", [f"dataset.pgt={tmp_path / 'pgt.txt'}"])):
        run = relocfw_here([*common, *extra, f"hydra.run.dir={tmp_path / name}"], tmp_path)
        assert run.returncode == 0, run.stderr
        summary = json.loads((tmp_path / name / "summary.json").read_text())
        runs[name] = {row["method"]: row for row in summary}
    baseline = "mean training pose"
    assert runs["pgt"][baseline]["median_position_m"] == pytest.approx(
        runs["own"][baseline]["median_position_m"], abs=1e-5
    )
    # The truth the run scored against is the file's: 2 m along x from .pose.txt's.
    truth = {}
    for name in ("own", "pgt"):
        with open(tmp_path / name / "results.csv") as stream:
            rows = [r for r in csv.DictReader(stream) if r["method"] == baseline]
        truth[name] = np.array([[float(r[f"true_{a}"]) for a in "xyz"] for r in rows])
    np.testing.assert_allclose(truth["pgt"] - truth["own"], [[2.0, 0, 0]] * 4, atol=1e-5)
    bad = relocfw_here(
        [*common, f"dataset.pgt={tmp_path / 'absent.txt'}", f"hydra.run.dir={tmp_path / 'bad'}"],
        tmp_path,
    )
    assert bad.returncode != 0
    assert f"file not found: {tmp_path / 'absent.txt'}" in bad.stderr
    assert "Traceback" not in bad.stderr


def test_split_files_that_share_a_sequence_are_refused(tiny_scene, tmp_path):
    """Not only the options: split files that put one sequence in map and queries are
    refused too (a validation run there would score frames its map holds)."""
    scene = tmp_path / "room"
    shutil.copytree(tiny_scene, scene)
    (scene / "TrainSplit.txt").write_text("sequence1\nsequence2\n")
    (scene / "TestSplit.txt").write_text("sequence2\n")
    with pytest.raises(ConfigError, match=r"share \[2\]: a test frame would be in the map"):
        SevenScenes(str(scene), None)


def test_a_file_without_a_splits_sequence_is_refused_before_training(tiny_scene, tmp_path):
    """The published references come as *_train.txt and *_test.txt: one of them alone
    leaves a split without poses, said when the dataset is made (not after training)."""
    path = tmp_path / "train_only.txt"
    truth = write_pgt(tiny_scene, path)
    lines = [line for line in path.read_text().splitlines() if not line.startswith("seq-03/")]
    path.write_text("\n".join(lines) + "\n")
    assert len(lines) < len(truth)
    with pytest.raises(DataError, match=r"has no line for sequence\(s\) \[3\] of .*TestSplit.txt"):
        SevenScenes(str(tiny_scene), None, pgt=str(path))
