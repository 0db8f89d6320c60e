"""task=localize: the model file's query options under query.*, and its files: poses.txt
in TUM format, with TUM timestamps where names are times."""

import csv

import cv2
import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_module

from relocfw import QueryOptions, Relocalizer
from relocfw.app.tasks.localize import load_for_localize, localize_images
from relocfw.core.errors import ConfigError, DataError
from relocfw.core.values import Crop, Localization, Pose
from relocfw.model.model_file import save_model
from relocfw.plugins.exhaustive_index import ExhaustiveIndex
from relocfw.plugins.posenet import PoseNet
from relocfw.plugins.sweep_crop import SweepCrop


class GreyLevelRelocalizer:
    """Answers x = the image's grey level, rotated 2 x grey level degrees about z."""

    def localize(self, image):
        level = float(image[0, 0, 0])
        half = np.radians(2 * level) / 2
        pose = Pose(np.array([level, 1.0, 2.0]), np.array([np.cos(half), 0, 0, np.sin(half)]))
        return Localization(pose, Crop(0, 0, 4), 0.25, 1, 0.0)

    options = QueryOptions(queries_at_once=2)  # images come in groups of two

    def localize_many(self, images, queries_at_once):
        assert len(images) <= queries_at_once == 2
        return [self.localize(image) for image in images]


def write_images(folder, names):
    folder.mkdir()
    paths = []
    for level, name in enumerate(names, start=10):
        path = folder / name
        cv2.imwrite(str(path), np.full((4, 6, 3), level, dtype=np.uint8))
        paths.append(path)
    return paths


def tum_rows(run_dir, name="poses.txt"):
    lines = (run_dir / name).read_text().splitlines()
    assert lines[0] == "# timestamp tx ty tz qx qy qz qw (camera-to-world)"
    return [line.split(" ") for line in lines[1:]]


@pytest.mark.parametrize(
    "names, stamps",
    [
        # TUM names images by their time: kept verbatim, digits and all.
        (
            ["1305031102.175304.png", "1305031102.211214.png"],
            ["1305031102.175304", "1305031102.211214"],
        ),
        (["17.png", "0018.jpg"], ["17", "0018"]),
        # Other names: the image's position in the list.
        (["frame-a.png", "frame-b.png", "frame-c.png"], ["0", "1", "2"]),
        (["1305031102.175304.png", "frame.png"], ["1305031102.175304", "1"]),
        # Names float() would take but TUM tools cannot read back.
        (["nan.png", "inf.png", "1_000.png", "1e5.png"], ["0", "1", "2", "3"]),
    ],
    ids=["tum times", "integers", "names", "mixed", "not plain decimals"],
)
def test_poses_txt_timestamps_are_numeric_names_or_positions(tmp_path, names, stamps):
    paths = write_images(tmp_path / "images", names)
    run_dir = tmp_path / "run"
    localize_images(GreyLevelRelocalizer(), paths, run_dir, quiet=True)
    rows = tum_rows(run_dir)
    assert [row[0] for row in rows] == stamps
    with open(run_dir / "localization.csv") as stream:
        table = list(csv.DictReader(stream))
    assert [row["timestamp"] for row in table] == stamps
    assert [row["image"] for row in table] == [str(p) for p in paths]


def test_poses_txt_rows_are_position_then_quaternion_with_w_last(tmp_path):
    paths = write_images(tmp_path / "images", ["1.png", "2.png"])
    localize_images(GreyLevelRelocalizer(), paths, tmp_path / "run", quiet=True)
    values = np.array([[float(v) for v in row] for row in tum_rows(tmp_path / "run")])
    for row, level in zip(values, (10, 11), strict=True):
        half = np.radians(2 * level) / 2
        assert np.allclose(row[1:4], [level, 1.0, 2.0])
        assert np.allclose(row[4:], [0.0, 0.0, np.sin(half), np.cos(half)])


# What the model file keeps: every option away from its default.
SAVED = QueryOptions(
    batch_size=4, scoring="shared", rerank=3, crop_samples=2, sample_seed=7, queries_at_once=2
)


@pytest.fixture(scope="module")
def saved_model(tmp_path_factory):
    torch.manual_seed(0)
    backbone = PoseNet(input_size=32, width=0.125, feature_dim=32)
    backbone.set_crop_scale(1.142857)  # crop sampling needs a crop larger than the view
    relocalizer = Relocalizer(backbone, ExhaustiveIndex(), SweepCrop(), SAVED)
    relocalizer.fit([np.zeros((36, 48, 3), np.uint8), np.full((36, 48, 3), 200, np.uint8)])
    options = {"backbone": {"input_size": 32, "width": 0.125, "feature_dim": 32}}
    path = tmp_path_factory.mktemp("model") / "model.relocfw"
    return save_model(path, relocalizer, options, {})


def localize_config(model, *overrides):
    """The config `relocfw task=localize localize.model=MODEL ...` composes."""
    with initialize_config_module(config_module="relocfw.conf", version_base="1.3"):
        return compose("config", overrides=["task=localize", f"localize.model={model}", *overrides])


def test_localize_keeps_the_model_files_query_options_where_query_is_null(saved_model):
    relocalizer = load_for_localize(localize_config(saved_model), torch.device("cpu"))
    assert relocalizer.options == SAVED


@pytest.mark.parametrize(
    "overrides, changed",
    [
        (["query.batch_size=9"], {"batch_size": 9}),
        (
            ["query.queries_at_once=1", "query.sample_seed=0"],
            {"queries_at_once": 1, "sample_seed": 0},
        ),
        (["query.crop_samples=0"], {"crop_samples": 0}),
        # Plain scoring makes the file's rerank moot: it falls back to 1.
        (["query.scoring=plain"], {"scoring": "plain", "rerank": 1}),
        (["query.rerank=5"], {"rerank": 5}),
    ],
)
def test_an_explicit_query_value_overrides_the_model_files(saved_model, overrides, changed):
    relocalizer = load_for_localize(localize_config(saved_model, *overrides), torch.device("cpu"))
    assert relocalizer.options == SAVED.replace(**changed)


def test_a_bad_query_value_for_localize_names_the_query_key(saved_model):
    cfg = localize_config(saved_model, "query.scoring=plain", "query.rerank=2")
    with pytest.raises(ConfigError, match=r"^query\.rerank=2 re-scores"):
        load_for_localize(cfg, torch.device("cpu"))


def test_rows_before_a_failing_image_are_on_disk(tmp_path):
    # Six images; the fifth (index 4) is corrupt: groups of two are answered, so
    # rows 0..3 were made before the run stops, and they must not be lost with it.
    paths = write_images(tmp_path / "images", [f"frame-{i}.png" for i in range(6)])
    paths[4].write_bytes(b"not a png")
    # A previous run's finished files under the final names are left as they were.
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "poses.txt").write_text("a finished run's poses\n")
    (run_dir / "localization.csv").write_text("a finished run's table\n")
    with pytest.raises(DataError, match="frame-4.png"):
        localize_images(GreyLevelRelocalizer(), paths, run_dir, quiet=True)
    assert [row[0] for row in tum_rows(run_dir, "poses.txt.partial")] == ["0", "1", "2", "3"]
    with open(run_dir / "localization.csv.partial") as stream:
        table = list(csv.DictReader(stream))
    assert [row["image"] for row in table] == [str(p) for p in paths[:4]]
    assert (run_dir / "poses.txt").read_text() == "a finished run's poses\n"
    assert (run_dir / "localization.csv").read_text() == "a finished run's table\n"
    # Finished, the same run leaves the final names only.
    paths[4].write_bytes((tmp_path / "images" / "frame-3.png").read_bytes())
    localize_images(GreyLevelRelocalizer(), paths, run_dir, quiet=True)
    assert len(tum_rows(run_dir)) == 6
    assert not any(run_dir.glob("*.partial"))


def test_a_bad_image_mid_group_keeps_the_rows_of_the_images_before_it(tmp_path):
    # Groups of two; image 3 is corrupt: image 2, its group-mate, is answered first.
    paths = write_images(tmp_path / "images", [f"frame-{i}.png" for i in range(5)])
    paths[3].write_bytes(b"not a png")
    with pytest.raises(DataError, match="frame-3.png"):
        localize_images(GreyLevelRelocalizer(), paths, tmp_path / "run", quiet=True)
    assert [row[0] for row in tum_rows(tmp_path / "run", "poses.txt.partial")] == ["0", "1", "2"]


def test_under_skip_a_bad_image_is_listed_and_the_rest_answered(tmp_path, capsys):
    paths = write_images(tmp_path / "images", [f"frame-{i}.png" for i in range(5)])
    paths[3].write_bytes(b"not a png")
    run_dir = tmp_path / "run"
    done = localize_images(GreyLevelRelocalizer(), paths, run_dir, quiet=True, on_error="skip")
    assert (done.localized, done.skipped) == (4, 1)
    # Positions stay the images' places in the list: the timestamps do not shift.
    assert [row[0] for row in tum_rows(run_dir)] == ["0", "1", "2", "4"]
    skipped = (run_dir / "skipped.txt").read_text().splitlines()
    assert len(skipped) == 1 and str(paths[3]) in skipped[0]
    assert "1 frames could not be decoded" in capsys.readouterr().err
    assert not any(run_dir.glob("*.partial"))


def test_an_unknown_on_error_is_a_config_error(tmp_path):
    paths = write_images(tmp_path / "images", ["0.png"])
    with pytest.raises(ConfigError, match=r"^localize\.on_error must be"):
        localize_images(GreyLevelRelocalizer(), paths, tmp_path / "run", on_error="ignore")
