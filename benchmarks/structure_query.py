"""Structure-based relocalization on real 7-Scenes frames: accuracy and time per query.

The map is the depth-built structure (relocfw.structure.build_from_depth) of the
training sequences (1, 3, 5, 7; every --map-every-th frame); the queries are
--queries frames spread evenly over the test sequences (2, 4, 6). Each query's
keyframes come from a ground-truth-free stand-in for retrieval: every image's
16 x 12 grey thumbnail, mean-subtracted and L2-normalised, and the map images of
highest cosine similarity (the pipeline will use the network's descriptor). Then
relocfw.structure.localize_against: RootSIFT of the query, one matching call against
the keyframes, PoseLib's LO-RANSAC.

Every combination of --threads (torch's and OpenCV's), --max-features and
--keyframes runs on every query, round robin (the orders rotate from query to query,
so a slow phase of the machine hits every setting alike). A query's features are
extracted once per thread count and --max-features and shared by its --keyframes
settings (passed as query_features); each setting's "features" time is that one
extraction. Errors count a failure (no pose) as
infinitely wrong: medians and the share within 5 cm / 5 deg are over all queries.

With --check-quantisation N, N pairs of training frames five frames apart are matched
with float32 map descriptors and with the uint8-quantised ones the map stores, and
the share of matches that differ is reported.

Maps are cached under --cache-dir (relocfw.structure.cached_structure_map), so a
rerun skips the build. Writes JSON atomically and prints a table.

    .venv/bin/python benchmarks/structure_query.py --map-every 2 --queries 60 --threads 1 2

Cameras as relocfw.data.sevenscenes gives them (scene_cameras): colour 525 for the
keypoints and queries, the depth camera (585, or camera-intrinsics.txt, read as the
depth sensor's) and the Kinect's depth-to-colour transform, so each depth map is
registered into its colour image before it is lifted (issue 43). The recorded
results (benchmarks/results/structure_query.json, docs/results/structure.md) predate
this: they lifted the raw depth at the colour pixel with one 585 camera for both.
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import platform
import time
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import torch
from common import DEFAULT_CACHE, write_json  # benchmarks/, the script's own folder

from relocfw.core.geometry import orientation_error_deg, pose_from_matrix
from relocfw.core.values import Pose
from relocfw.data.sevenscenes import SceneCameras, read_pose_file, scene_cameras
from relocfw.structure import (
    MapView,
    StructureMap,
    build_from_depth,
    cached_structure_map,
    extract_rootsift,
    localize_against,
    mutual_nearest_neighbours,
    structure_key,
)
from relocfw.structure.structure_map import on_descriptor_grid

TRAIN_SEQUENCES = (1, 3, 5, 7)
TEST_SEQUENCES = (2, 4, 6)
THUMBNAIL = (16, 12)  # width, height
WITHIN_M = 0.05
WITHIN_DEG = 5.0


def read_rgb_cv2(path: Path) -> np.ndarray:
    """[H, W, 3] uint8 RGB of an image file (cv2 reads BGR: reversed here)."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise SystemExit(f"cannot read image {path}")
    return np.ascontiguousarray(image[:, :, ::-1])


class Frame:
    """One 7-Scenes frame: its files, name and ground-truth pose."""

    def __init__(self, scene: Path, sequence: int, number: int) -> None:
        stem = scene / f"seq-{sequence:02d}" / f"frame-{number:06d}"
        self.colour = Path(f"{stem}.color.jpg")
        self.depth = Path(f"{stem}.depth.png")
        pose_file = Path(f"{stem}.pose.txt")
        self.pose: Pose = pose_from_matrix(read_pose_file(pose_file), str(pose_file))
        self.name = f"seq-{sequence:02d}/frame-{number:06d}"


class LazyViews(Sequence):
    """Map views that read their image only when asked (the builders read each once),
    so the map's images are never all in memory together."""

    def __init__(self, frames: list[Frame], cameras: SceneCameras) -> None:
        self.frames = frames
        self.cameras = cameras

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> MapView:  # type: ignore[override]
        frame = self.frames[index]
        return MapView(
            read_rgb_cv2(frame.colour),
            frame.pose,
            self.cameras.colour,
            frame.depth,
            frame.name,
            depth_camera=self.cameras.depth,
            depth_to_colour=self.cameras.depth_to_colour,
        )


def frames_of(scene: Path, sequences: Sequence[int]) -> list[Frame]:
    """Every frame of the sequences, in order."""
    frames = []
    for sequence in sequences:
        folder = scene / f"seq-{sequence:02d}"
        numbers = sorted(int(p.name[6:12]) for p in folder.glob("frame-*.color.jpg"))
        if not numbers:
            raise SystemExit(f"no frames in {folder}")
        frames += [Frame(scene, sequence, n) for n in numbers]
    return frames


def thumbnail(image: np.ndarray) -> np.ndarray:
    """The retrieval stand-in: a 16 x 12 grey thumbnail, mean-subtracted, unit norm."""
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    small = cv2.resize(grey, THUMBNAIL, interpolation=cv2.INTER_AREA).astype(np.float32).ravel()
    small -= small.mean()
    return small / max(float(np.linalg.norm(small)), 1e-6)


def quantisation_effect(frames: list[Frame], pairs: int, max_features: int) -> dict:
    """How many matches change when the map side's descriptors are the stored uint8."""
    step = max(1, (len(frames) - 5) // pairs)
    same = float_total = quantised_total = 0
    for index in range(0, step * pairs, step):
        first, second = frames[index], frames[min(index + 5, len(frames) - 1)]
        query = extract_rootsift(read_rgb_cv2(first.colour), max_features)
        mapped = extract_rootsift(read_rgb_cv2(second.colour), max_features)
        exact = {tuple(m) for m in mutual_nearest_neighbours(query.descriptors, mapped.descriptors)}
        stored = on_descriptor_grid(mapped).descriptors
        rounded = {tuple(m) for m in mutual_nearest_neighbours(query.descriptors, stored)}
        same += len(exact & rounded)
        float_total += len(exact)
        quantised_total += len(rounded)
    return {
        "pairs": pairs,
        "max_features": max_features,
        "matches_float32": float_total,
        "matches_uint8": quantised_total,
        "lost_share": 1 - same / max(float_total, 1),
        "new_share": (quantised_total - same) / max(float_total, 1),
    }


def pose_errors(estimate: Pose | None, truth: Pose) -> tuple[float, float]:
    """(position error in metres, orientation error in degrees); infinite for no pose."""
    if estimate is None:
        return math.inf, math.inf
    return (
        float(np.linalg.norm(estimate.position - truth.position)),
        float(orientation_error_deg(estimate.quaternion, truth.quaternion)),
    )


def relative(row: dict, reference: dict | None) -> float | None:
    """A setting's median position error over the reference setting's (None where
    either is missing or infinite)."""
    if not (reference and reference["median_position_m"] and row["median_position_m"]):
        return None
    return row["median_position_m"] / reference["median_position_m"]


def set_threads(count: int) -> None:
    """Threads for torch (matching) and OpenCV (SIFT)."""
    torch.set_num_threads(count)
    cv2.setNumThreads(count)


def finite_or_none(value: float) -> float | None:
    """`value`, or None where it is infinite (JSON has no infinity)."""
    return value if math.isfinite(value) else None


def summary(errors: list[tuple[float, float]], seconds: list[dict], inliers: list[int]) -> dict:
    """Accuracy (failures as infinite errors) and median times of one setting."""
    position = np.array([e[0] for e in errors])
    rotation = np.array([e[1] for e in errors])
    parts = {
        part: 1000 * float(np.median([s[part] for s in seconds]))
        for part in ("features", "matching", "solve")
    }
    return {
        "queries": len(errors),
        "failures": int(np.isinf(position).sum()),
        "median_position_m": finite_or_none(float(np.median(position))),
        "median_rotation_deg": finite_or_none(float(np.median(rotation))),
        "within_5cm_5deg": float(np.mean((position <= WITHIN_M) & (rotation <= WITHIN_DEG))),
        "median_inliers": float(np.median(inliers)),
        "median_ms": {
            **parts,
            "total": 1000 * float(np.median([sum(s.values()) for s in seconds])),
        },
        "mean_total_ms": 1000 * float(np.mean([sum(s.values()) for s in seconds])),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("/work/shared/data/7scenes-redkitchen"))
    parser.add_argument("--scene", default="redkitchen")
    parser.add_argument("--map-every", type=int, default=2, help="every N-th training frame")
    parser.add_argument("--queries", type=int, default=60)
    parser.add_argument("--max-features", type=int, nargs="+", default=[1024, 2048])
    parser.add_argument("--keyframes", type=int, nargs="+", default=[5, 10])
    parser.add_argument(
        "--threads", type=int, nargs="+", default=[1, 2], help="torch and OpenCV threads"
    )
    parser.add_argument("--check-quantisation", type=int, default=20, metavar="PAIRS")
    parser.add_argument("--cache-dir", type=Path, default=DEFAULT_CACHE)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/structure_query.json"))
    args = parser.parse_args()
    if args.map_every < 1 or args.queries < 1 or min(args.threads) < 1:
        parser.error("--map-every, --queries and --threads must be at least 1")
    set_threads(args.threads[0])
    load_before = os.getloadavg()[0]

    scene = args.data / args.scene
    map_frames = frames_of(scene, TRAIN_SEQUENCES)[:: args.map_every]
    # camera-intrinsics.txt (scene folder or --data) describes the depth sensor.
    cameras = scene_cameras(scene, [f.colour for f in map_frames], intrinsics_for="depth")
    camera = cameras.colour
    test_frames = frames_of(scene, TEST_SEQUENCES)
    picks = np.linspace(0, len(test_frames) - 1, min(args.queries, len(test_frames)))
    queries = [test_frames[int(round(i))] for i in picks]
    views = LazyViews(map_frames, cameras)

    maps: dict[int, StructureMap] = {}
    build_seconds: dict[int, float | None] = {}
    map_bytes: dict[int, int] = {}
    for max_features in args.max_features:
        settings = {
            "builder": "depth",
            "max_features": max_features,
            "data": str(scene),
            "depth": "registered",  # maps cached before registration are not reused
        }
        key = structure_key(
            [f.name for f in map_frames], [f.pose for f in map_frames], [camera] * len(map_frames),
            settings,
        )  # fmt: skip
        built: list[float] = []

        def build(max_features: int = max_features, built: list[float] = built) -> StructureMap:
            start = time.perf_counter()
            structure = build_from_depth(views, max_features=max_features)
            built.append(time.perf_counter() - start)
            return structure

        maps[max_features] = cached_structure_map(args.cache_dir, key, build)
        build_seconds[max_features] = built[0] if built else None
        map_bytes[max_features] = (
            (args.cache_dir / "structure" / f"{key}.npz").expanduser().stat().st_size
        )
        for skipped in maps[max_features].skipped_views:
            print(f"  skipped {skipped.name}: {skipped.reason}")

    map_thumbnails = np.stack([thumbnail(read_rgb_cv2(f.colour)) for f in map_frames])
    settings_list = list(itertools.product(args.threads, args.max_features, args.keyframes))
    errors: dict[tuple, list] = {s: [] for s in settings_list}
    seconds: dict[tuple, list] = {s: [] for s in settings_list}
    inliers: dict[tuple, list] = {s: [] for s in settings_list}
    retrieval_seconds = []
    started = time.perf_counter()
    for number, frame in enumerate(queries):
        image = read_rgb_cv2(frame.colour)
        start = time.perf_counter()
        similarity = map_thumbnails @ thumbnail(image)
        ranked = np.argsort(-similarity, kind="stable")
        retrieval_seconds.append(time.perf_counter() - start)
        # Round robin: rotate every order from query to query.
        for threads in np.roll(args.threads, number).tolist():
            set_threads(threads)
            for max_features in np.roll(args.max_features, number).tolist():
                start = time.perf_counter()
                features = extract_rootsift(image, max_features)
                extraction = time.perf_counter() - start
                for count in np.roll(args.keyframes, number).tolist():
                    answer = localize_against(
                        maps[max_features],
                        None,
                        camera,
                        ranked[:count].tolist(),
                        max_features=max_features,
                        query_features=features,
                    )
                    setting = (threads, max_features, count)
                    seconds[setting].append({**answer.seconds, "features": extraction})
                    inliers[setting].append(answer.inliers)
                    errors[setting].append(pose_errors(answer.pose, frame.pose))
        if (number + 1) % 10 == 0:
            print(f"  {number + 1}/{len(queries)} queries, {time.perf_counter() - started:.0f} s")

    rows = {s: summary(errors[s], seconds[s], inliers[s]) for s in settings_list}
    references = {t: rows.get((t, 1024, 10)) for t in args.threads}
    quantisation = (
        quantisation_effect(
            frames_of(scene, TRAIN_SEQUENCES), args.check_quantisation, args.max_features[0]
        )
        if args.check_quantisation > 0
        else None
    )
    load = os.getloadavg()
    print(
        f"{len(queries)} queries of {args.scene} seq {TEST_SEQUENCES}, map of {len(map_frames)} "
        f"frames (seq {TRAIN_SEQUENCES}, every {args.map_every}), load average "
        f"{load_before:.1f} before, {load[0]:.1f} after"
    )
    print(
        f"{'threads':>7} {'features':>8} {'kf':>3} {'fail':>4} {'med pos':>8} {'med rot':>8} "
        f"{'5cm5deg':>8} "
        f"{'inliers':>7} {'feat ms':>8} {'match ms':>8} {'solve ms':>8} {'total ms':>8}"
    )
    for (threads, max_features, count), row in rows.items():
        ms = row["median_ms"]
        print(
            f"{threads:>7} {max_features:>8} {count:>3} {row['failures']:>4} "
            f"{100 * (row['median_position_m'] or math.inf):>6.2f}cm "
            f"{row['median_rotation_deg'] or math.inf:>6.2f}d "
            f"{row['within_5cm_5deg']:>8.1%} {row['median_inliers']:>7.0f} {ms['features']:>8.1f} "
            f"{ms['matching']:>8.1f} {ms['solve']:>8.1f} {ms['total']:>8.1f}"
        )
    print(f"retrieval stand-in: median {1000 * float(np.median(retrieval_seconds)):.2f} ms")
    if quantisation is not None:
        print(
            f"uint8 descriptors vs float32 on {quantisation['pairs']} map pairs: "
            f"{quantisation['lost_share']:.2%} of {quantisation['matches_float32']} matches lost, "
            f"{quantisation['new_share']:.2%} new"
        )
    report = {
        "data": str(scene),
        "map_frames": len(map_frames),
        "map_every": args.map_every,
        "queries": len(queries),
        "threads": args.threads,
        "load_average_1min": {"before": load_before, "after": load[0]},
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores",
        "retrieval": f"{THUMBNAIL[0]}x{THUMBNAIL[1]} grey thumbnails, cosine nearest",
        "retrieval_median_ms": 1000 * float(np.median(retrieval_seconds)),
        "maps": {
            str(f): {
                "images": len(maps[f]),
                "points": int(maps[f].point_counts().sum()),
                "skipped_views": len(maps[f].skipped_views),
                "build_seconds": build_seconds[f],
                "file_bytes": map_bytes[f],
            }
            for f in args.max_features
        },
        "settings": [
            {
                "threads": t,
                "max_features": f,
                "keyframes": k,
                **row,
                "median_position_vs_1024_10": relative(row, references[t]),
            }
            for (t, f, k), row in rows.items()
        ],
        "quantisation": quantisation,
    }
    write_json(report, args.out)


if __name__ == "__main__":
    main()
