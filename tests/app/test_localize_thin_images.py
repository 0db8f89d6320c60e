"""query.max_aspect and query.max_candidates from the command line to the pipeline:
task=localize refuses a thin frame as a frame (on_error=skip lists it; a file on its
header, a stream's frame on its pixels), a raised max_aspect lets it through, and
the candidate cap then refuses it in one line naming its key."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from relocfw.app.tasks.localize import localize_frames
from relocfw.data.stream_frame import StreamFrame
from tests.app.test_localize_streams import localize
from tests.data.test_ros_images import model  # noqa: F401  (a fixture: the tiny model)


@pytest.fixture
def images(tmp_path):
    """A folder of two 36 x 48 frames and, between them, a 1 x 200 strip."""
    folder = tmp_path / "images"
    folder.mkdir()
    for name, (height, width) in (("a", (36, 48)), ("b", (1, 200)), ("c", (36, 48))):
        pixels = np.random.default_rng(len(name)).integers(0, 256, (height, width, 3))
        cv2.imwrite(str(folder / f"{name}.png"), pixels.astype(np.uint8))
    return folder


def test_a_thin_file_is_listed_under_skip_and_a_raised_limit_localizes_it(
    model,  # noqa: F811
    images,
    tmp_path,
):
    skipped_run = tmp_path / "skip"
    result = localize(model, images, skipped_run, "localize.on_error=skip")
    assert result.returncode == 0, result.stderr
    (skipped,) = (skipped_run / "skipped.txt").read_text().splitlines()
    assert skipped.startswith(f"{images / 'b.png'}: its header announces 200 x 1 pixels")
    assert "query.max_aspect=10 allows" in skipped

    raised = tmp_path / "raised"
    result = localize(model, images, raised, "query.max_aspect=300")
    assert result.returncode == 0, result.stderr
    table = (raised / "localization.csv").read_text()
    assert str(images / "b.png") in table


CAPPED = ("query.max_aspect=300", "query.max_candidates=100", "query.queries_at_once=2")


def test_a_query_refused_after_its_header_is_a_skipped_frame_in_a_group(
    model,  # noqa: F811
    images,
    tmp_path,
):
    # b.png (200 x 1) asks for 200 windows, past query.max_candidates=100; it is
    # grouped with a.png (queries_at_once=2), which is still answered.
    skipped_run = tmp_path / "skip"
    result = localize(model, images, skipped_run, *CAPPED, "localize.on_error=skip")
    assert result.returncode == 0, result.stderr
    (skipped,) = (skipped_run / "skipped.txt").read_text().splitlines()
    assert skipped.startswith(
        f"{images / 'b.png'}: the crop search asks for 200 candidate windows of the 200 x 1 "
        "query image, more than query.max_candidates=100 allows"
    )
    table = (skipped_run / "localization.csv").read_text()
    assert str(images / "a.png") in table and str(images / "c.png") in table
    assert str(images / "b.png") not in table

    capped = tmp_path / "capped"
    result = localize(model, images, capped, *CAPPED)
    assert result.returncode == 2
    assert result.stderr.splitlines()[-1].startswith(
        f"error: {images / 'b.png'}: the crop search asks for 200 candidate windows"
    )
    rows = (capped / "localization.csv.partial").read_text()  # the frame before it kept
    assert str(images / "a.png") in rows and str(images / "b.png") not in rows


def test_a_thin_frame_of_a_stream_is_refused_on_its_pixels_as_a_frame(tmp_path):
    class Answering:
        def localize(self, image):
            raise AssertionError("a thin frame reached the pipeline")

    frames = [StreamFrame("run.mp4#0", "0.000000000", np.zeros((1, 20, 3), np.uint8))]
    run = localize_frames(Answering(), frames, tmp_path, quiet=True, on_error="skip")
    assert (run.localized, run.skipped) == (0, 1)
    (skipped,) = (tmp_path / "skipped.txt").read_text().splitlines()
    assert skipped.startswith("run.mp4#0 is 20 x 1 pixels, its long side 20 times")
