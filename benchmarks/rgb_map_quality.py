"""How good the RGB-only map is: two-view medians against multi-view tracks (and depth).

Map: Red Kitchen training sequences 1, 3, 5, 7 (/work/shared/data/7scenes-redkitchen),
every --step-th frame, as relocfw.data.sevenscenes loads them: the colour camera
PinholeCamera(525, 525, 320, 240, 640, 480) and the depth camera (585) with the
depth-to-colour transform, so depth is registered into the colour image before it
is read (relocfw.structure.registration; issue 43). The map is built four ways:
relocfw.structure.build_by_triangulation with method two_view (the earlier builder)
and method tracks (the default), build_from_depth, and pycolmap's fixed-pose
triangulation ("colmap": relocfw.data.colmap_triangulation, SIFT, every pair of map
images matched and verified, tracks triangulated and bundle adjusted with the poses
held, as hloc does; its points then given to relocfw's RootSIFT keypoints by
build_from_colmap_points; --no-colmap leaves it out). Per map: the share of
keypoints with a 3-D point, the map's points' error against the points lifted with
the same keypoints' registered depth (relocfw.structure.map_quality), and the
build's seconds (features included). For the colmap row also the COLMAP model's
own: the share of its SIFT keypoints with a 3-D point and its observations' error
against registered depth.

Query stand-in: --queries frames of test sequence 2, spread evenly; each is matched
against the --keyframes map images nearest its GROUND-TRUTH pose (keyframes_by_pose:
an oracle retrieval, so the rows compare maps, not retrieval) and solved with
localize_against (PoseLib LO-RANSAC). Median position and orientation error over
solved queries, share within 5 cm / 5 deg (a failure counts as outside), failures.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/rgb_map_quality.py --step 2 --queries 50
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import LazyViews, write_json
from relocfw.core.camera import PinholeCamera
from relocfw.core.geometry import orientation_error_deg, position_error
from relocfw.core.imaging import read_rgb
from relocfw.core.observations import PointObservations
from relocfw.data.colmap_format import ColmapCamera
from relocfw.data.colmap_points import read_model_observations
from relocfw.data.colmap_triangulation import pycolmap_module, triangulate_posed_images
from relocfw.data.frames import Frame
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.structure import (
    StructureMap,
    build_by_triangulation,
    build_from_depth,
    keyframes_by_pose,
    localize_against,
)
from relocfw.structure.colmap_structure import build_from_colmap_points
from relocfw.structure.depth_structure import depth_of_view
from relocfw.structure.lifting import lift_keypoints
from relocfw.structure.map_quality import depth_agreement, point_share

ROOT = Path("/work/shared/data/7scenes-redkitchen")
SCENE = ROOT / "redkitchen"
COLOUR_CAMERA = PinholeCamera(525.0, 525.0, 320.0, 240.0, 640, 480)
# The same camera in COLMAP's pixels, which start at the top-left pixel's corner.
COLMAP_CAMERA = ColmapCamera(1, "PINHOLE", 640, 480, (525.0, 525.0, 320.5, 240.5))
WITHIN_M = 0.05
WITHIN_DEG = 5.0


def colmap_observations(
    frames: list[Frame], max_features: int
) -> tuple[list[PointObservations], int]:
    """Per map frame, the points pycolmap's fixed-pose triangulation gave it, and how
    many SIFT keypoints the model's images hold in all."""
    pycolmap_module().logging.minloglevel = 2
    names = [str(frame.image_path.relative_to(SCENE)) for frame in frames]
    with tempfile.TemporaryDirectory(prefix="rgb_map_quality_colmap_") as workspace:
        model = triangulate_posed_images(
            SCENE,
            names,
            [frame.pose for frame in frames],
            COLMAP_CAMERA,
            Path(workspace) / "colmap",
            max_features,
        )
        reconstruction = pycolmap_module().Reconstruction(str(model))
        keypoints = sum(image.num_points2D() for image in reconstruction.images.values())
        seen = read_model_observations(model / "images.bin")
    empty = PointObservations(np.zeros((0, 2)), np.zeros((0, 3)), np.zeros(0, np.int64))
    return [seen.get(name, empty) for name in names], int(keypoints)


def colmap_model_rows(
    observations: list[PointObservations], keypoints: int, views: LazyViews
) -> dict:
    """The COLMAP model's own share of keypoints with a point (its SIFT keypoints are
    at most max_features per image) and its observations against registered depth."""
    errors = []
    for index, (seen, frame) in enumerate(zip(observations, views.frames, strict=True)):
        if not len(seen):
            continue
        depth, _ = depth_of_view(views[index])
        if depth is None:
            continue
        lifted = lift_keypoints(seen.keypoints, depth, frame.camera, frame.pose)
        both = np.isfinite(lifted).all(axis=1)
        errors.append(np.linalg.norm(seen.points[both] - lifted[both], axis=1))
    distance = np.concatenate(errors) if errors else np.zeros(0)
    observed = int(sum(len(seen) for seen in observations))
    return {
        "sift_keypoints": keypoints,
        "observations": observed,
        "share_with_point": observed / keypoints if keypoints else 0.0,
        "points": int(len({int(i) for seen in observations for i in seen.track_ids})),
        "compared": int(len(distance)),
        "median_error_m": float(np.median(distance)) if len(distance) else float("nan"),
        "within_5cm": float(np.mean(distance <= 0.05)) if len(distance) else float("nan"),
    }


def query_errors(
    structure: StructureMap, queries: list[Frame], keyframes: int, **solver
) -> tuple[np.ndarray, np.ndarray]:
    """Each query's position (m) and orientation (deg) error, solved against the
    `keyframes` map images nearest its ground-truth pose with `solver` passed to
    localize_against; inf where it failed."""
    positions, angles = [], []
    for frame in queries:
        chosen = keyframes_by_pose(structure, frame.pose, keyframes)
        answer = localize_against(
            structure, read_rgb(frame.image_path), frame.camera, chosen, **solver
        )
        if not answer.success:
            positions.append(np.inf)
            angles.append(np.inf)
            continue
        positions.append(float(position_error(answer.pose.position, frame.pose.position)))
        angles.append(float(orientation_error_deg(answer.pose.quaternion, frame.pose.quaternion)))
    return np.array(positions), np.array(angles)


def query_rows(structure: StructureMap, queries: list[Frame], keyframes: int) -> dict:
    """Median errors, share within 5 cm / 5 deg and failures of the query stand-in."""
    positions_a, angles_a = query_errors(structure, queries, keyframes)
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
    if structure.source != "depth":
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
    parser.add_argument(
        "--no-colmap", action="store_true", help="leave out pycolmap's triangulation"
    )
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/rgb_map_quality.json"))
    args = parser.parse_args()

    # The recorded results were measured with the nominal 525 colour camera.
    train = load_sevenscenes(ROOT, "redkitchen", "train", colour_focal=COLOUR_CAMERA.fx)
    train = train[:: args.step]
    test = load_sevenscenes(
        ROOT, "redkitchen", "test", sequences=[2], colour_focal=COLOUR_CAMERA.fx
    )
    if train[0].camera != COLOUR_CAMERA or train[0].depth_camera is None:
        raise SystemExit(f"expected the loader's colour camera {COLOUR_CAMERA} and a depth camera")
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
    if not args.no_colmap:
        model: dict = {}

        def colmap_build() -> StructureMap:
            model["observed"], model["keypoints"] = colmap_observations(train, args.max_features)
            return build_from_colmap_points(views, model["observed"], args.max_features, quiet=True)

        row = measure("colmap", colmap_build, views, queries, args.keyframes)
        row["colmap_model"] = colmap_model_rows(model["observed"], model["keypoints"], views)
        print(row["colmap_model"], flush=True)
        rows.append(row)
    report = {
        "benchmark": "rgb_map_quality",
        "data": str(ROOT),
        "map_frames": len(train),
        "map_sequences": [1, 3, 5, 7],
        "step": args.step,
        "colour_camera": dataclasses.asdict(COLOUR_CAMERA),
        "depth_camera": dataclasses.asdict(train[0].depth_camera),
        "depth_reference": "depth registered into the colour image (depth camera, transform)",
        "colmap": None if args.no_colmap else "exhaustive pairs, SIFT max_features, poses fixed",
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
