"""How good the RGB-only map is: two-view medians against multi-view tracks (and depth).

Map: Red Kitchen training sequences 1, 3, 5, 7 (/work/shared/data/7scenes-redkitchen),
every --step-th frame. Every frame's colour camera is set to
PinholeCamera(525, 525, 320, 240, 640, 480): 7-Scenes' colour focal length (the
dataset file holds the depth camera's 585; issue 43). The map is built three ways:
relocfw.structure.build_by_triangulation with method two_view (the earlier builder)
and method tracks (the default), and build_from_depth. Per map: the share of
keypoints with a 3-D point, the triangulated points' error against the points lifted
with the same keypoints' depth (plain depth read at the colour pixel, not
registered: relocfw.structure.map_quality), and the build's seconds (features
included).

Query stand-in: --queries frames of test sequence 2, spread evenly; each is matched
against the --keyframes map images nearest its GROUND-TRUTH pose (keyframes_by_pose:
an oracle retrieval, so the rows compare maps, not retrieval) and solved with
localize_against (PoseLib LO-RANSAC). Median position and orientation error over
solved queries, share within 5 cm / 5 deg (a failure counts as outside), failures.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/rgb_map_quality.py --step 2 --queries 50

pycolmap's fixed-pose triangulation (hloc's) is not measured here.
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from benchmarks.common import write_json
from relocfw.core.camera import PinholeCamera
from relocfw.core.geometry import orientation_error_deg, position_error
from relocfw.core.imaging import read_rgb
from relocfw.data.frames import Frame
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.structure import (
    StructureMap,
    build_by_triangulation,
    build_from_depth,
    keyframes_by_pose,
    localize_against,
)
from relocfw.structure.map_quality import depth_agreement, point_share
from relocfw.structure.map_view import MapView

ROOT = Path("/work/shared/data/7scenes-redkitchen")
COLOUR_CAMERA = PinholeCamera(525.0, 525.0, 320.0, 240.0, 640, 480)
WITHIN_M = 0.05
WITHIN_DEG = 5.0


class LazyViews(Sequence):
    """Map views that read their image when asked (each builder reads each once)."""

    def __init__(self, frames: list[Frame]) -> None:
        self.frames = frames

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> MapView:  # type: ignore[override]
        frame = self.frames[index]
        return MapView(
            read_rgb(frame.image_path), frame.pose, frame.camera, frame.depth_path, frame.name
        )


def with_colour_camera(frames: list[Frame]) -> list[Frame]:
    """The frames with 7-Scenes' colour camera (focal 525) instead of the file's 585."""
    return [dataclasses.replace(frame, camera=COLOUR_CAMERA) for frame in frames]


def query_rows(structure: StructureMap, queries: list[Frame], keyframes: int) -> dict:
    """Median errors, share within 5 cm / 5 deg and failures of the query stand-in."""
    positions, angles = [], []
    for frame in queries:
        chosen = keyframes_by_pose(structure, frame.pose, keyframes)
        answer = localize_against(structure, read_rgb(frame.image_path), COLOUR_CAMERA, chosen)
        if not answer.success:
            positions.append(np.inf)
            angles.append(np.inf)
            continue
        positions.append(float(position_error(answer.pose.position, frame.pose.position)))
        angles.append(float(orientation_error_deg(answer.pose.quaternion, frame.pose.quaternion)))
    positions_a, angles_a = np.array(positions), np.array(angles)
    solved = np.isfinite(positions_a)
    return {
        "queries": len(queries),
        "failures": int((~solved).sum()),
        "median_position_m": float(np.median(positions_a)),
        "median_orientation_deg": float(np.median(angles_a)),
        "within_5cm_5deg": float(np.mean((positions_a <= WITHIN_M) & (angles_a <= WITHIN_DEG))),
    }


def measure(name: str, build, views: LazyViews, queries: list[Frame], keyframes: int) -> dict:
    start = time.perf_counter()
    structure = build()
    seconds = time.perf_counter() - start
    row = {
        "map": name,
        "build_seconds": round(seconds, 1),
        "keypoints": int(sum(len(f) for f in structure.features)),
        "share_with_point": point_share(structure),
        "skipped_views": len(structure.skipped_views),
    }
    if structure.source == "triangulated":
        agreement = depth_agreement(structure, views)
        row["against_depth"] = dataclasses.asdict(agreement)
    if queries:
        row["query"] = query_rows(structure, queries, keyframes)
    print(row, flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--step", type=int, default=2, help="every step-th training frame")
    parser.add_argument("--queries", type=int, default=50, help="test frames of seq 2")
    parser.add_argument("--keyframes", type=int, default=10)
    parser.add_argument("--max-features", type=int, default=1024)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/rgb_map_quality.json"))
    args = parser.parse_args()

    train = with_colour_camera(load_sevenscenes(ROOT, "redkitchen", "train"))[:: args.step]
    test = with_colour_camera(load_sevenscenes(ROOT, "redkitchen", "test", sequences=[2]))
    picks = np.linspace(0, len(test) - 1, args.queries).round().astype(int) if args.queries else []
    queries = [test[i] for i in sorted(set(int(i) for i in picks))]
    views = LazyViews(train)
    rows = []
    for name, build in (
        (
            "two_view",
            lambda: build_by_triangulation(views, args.max_features, method="two_view", quiet=True),
        ),
        (
            "tracks",
            lambda: build_by_triangulation(views, args.max_features, method="tracks", quiet=True),
        ),
        ("depth", lambda: build_from_depth(views, args.max_features, quiet=True)),
    ):
        rows.append(measure(name, build, views, queries, args.keyframes))
    report = {
        "benchmark": "rgb_map_quality",
        "data": str(ROOT),
        "map_frames": len(train),
        "map_sequences": [1, 3, 5, 7],
        "step": args.step,
        "colour_camera": dataclasses.asdict(COLOUR_CAMERA),
        "depth_reference": "plain depth read at the colour pixel (not registered)",
        "query_retrieval": "oracle: keyframes nearest the ground-truth pose",
        "query_sequence": 2,
        "keyframes": args.keyframes,
        "max_features": args.max_features,
        "machine": platform.machine(),
        "rows": rows,
    }
    write_json(report, args.out)


if __name__ == "__main__":
    main()
