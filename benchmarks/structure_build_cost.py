"""What the structure-based stage costs: building the map's features, and one query.

Build: for each of --map-sizes, relocfw.structure.build_from_depth on real Red Kitchen
frames (RootSIFT extraction, keypoints lifted to 3-D with the Kinect depth, descriptors
put on the stored uint8 grid, the StructureMap assembled), then StructureMap.save. The
sample has 700 real frames (all seven sequences); a map of up to 700 images takes
distinct frames spread evenly over the recording, a larger one cycles through them
(10^4 reuses each frame about 14 times, each as a distinct map view with its own name,
`seq-01/frame-000000#r3`): the cost does not depend on the images being distinct; the
map then holds repeated views. (Cycled files are read through the OS's file cache.)

build_from_depth is one loop over the views. Its parts are timed by wrapping the
module-level functions it calls (extract_rootsift: features; on_descriptor_grid:
quantisation; depth_judged: depth read; lift_keypoints: lifting) and the lazy view
sequence it reads (image read: JPEG decode), so the numbers are the real builder's;
"assembly" is the rest of the build (the StructureMap's checks and copies, the loop).
Memory is the process's peak resident set (ru_maxrss) before the build, after it and
after the save: sizes run in ascending order and each map is freed before the next, so
a larger map's values are its own. StructureMap.save peaks at about four times the
map's float32 descriptors (it concatenates them, and quantising makes two float32
temporaries), so before each build the script forecasts that peak from the previous
size and stops when it would not fit (--ignore-memory-forecast builds anyway). The map
file goes to a temporary folder (removed afterwards) unless --map-dir is given.

With --extrapolate-from N, each size above N is built from N of its views (evenly
spaced over them) and every time, count and size is scaled by size / N; such rows say
"extrapolated" in the JSON and the table (peak memory stays the measured one).

Query: --queries test frames (sequences 2, 4, 6, spread evenly) are localized against
the largest map of distinct frames (700 by default) with localize_against
(relocfw.structure), as benchmarks/structure_query.py does: the --keyframes map images of highest
thumbnail similarity (its ground-truth-free retrieval stand-in), then RootSIFT of the
query, one matching call, PoseLib's LO-RANSAC. That map holds the test frames too, so
the keyframes are ranked among its training-sequence views only (1, 3, 5, 7): a query
never matches its own frame, and the errors compare with structure_query.py's. Median
ms of features, matching, solve and their total, and the median errors (a failure is
infinitely wrong).

Writes JSON atomically after every stage ("complete" false until the end, so a run
cut short keeps what it measured) and prints Markdown tables.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/structure_build_cost.py \\
        --map-sizes 700 10000 --queries 30 --threads 1
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import gc
import math
import os
import platform
import resource
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np
import poselib
import torch
from common import write_json  # benchmarks/, the script's own folder
from structure_query import (
    TEST_SEQUENCES,
    THUMBNAIL,
    TRAIN_SEQUENCES,
    Frame,
    LazyViews,
    frames_of,
    pose_errors,
    read_rgb_cv2,
    set_threads,
    summary,
    thumbnail,
)

from relocfw.core.camera import PinholeCamera
from relocfw.data.sevenscenes import SceneCameras, scene_cameras
from relocfw.structure import MapView, StructureMap, build_from_depth, localize_against
from relocfw.structure import depth_structure as structure_module

ALL_SEQUENCES = tuple(range(1, 8))
# The functions build_from_depth looks up in its module, and the part each one is.
WRAPPED_PARTS = {
    "extract_rootsift": "features",
    "on_descriptor_grid": "quantisation",
    "depth_judged": "depth_read",
    "lift_keypoints": "lifting",
}
BUILD_PARTS = ("image_read", *WRAPPED_PARTS.values(), "assembly")
REPEATS_NOTE = (
    "maps larger than the real frames cycle through them, each reuse a distinct map view "
    "with its own name: cost does not depend on the images being distinct; the map then "
    "holds repeated views"
)
# StructureMap.save concatenates the float32 descriptors, then quantising makes two
# float32 temporaries of that size: about four times the map's descriptors at its peak.
SAVE_PEAK_FACTOR = 4
MIB = 2**20


class TimedViews(LazyViews):
    """LazyViews that add the time of each image read (and MapView check) to a dict."""

    def __init__(self, frames: list[Frame], cameras: SceneCameras, seconds: dict) -> None:
        super().__init__(frames, cameras)
        self.seconds = seconds

    def __getitem__(self, index: int) -> MapView:  # type: ignore[override]
        start = time.perf_counter()
        try:
            return super().__getitem__(index)
        finally:
            self.seconds["image_read"] += time.perf_counter() - start


def timed(function: Callable, part: str, seconds: dict, calls: dict) -> Callable:
    """`function`, adding each call's time to seconds[part] and counting its calls."""

    def call(*args, **kwargs):
        start = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            seconds[part] += time.perf_counter() - start
            calls[part] += 1

    return call


@contextlib.contextmanager
def timed_build_parts(seconds: dict, calls: dict) -> Iterator[None]:
    """Time build_from_depth's parts by wrapping the functions it calls.

    Wrapping the names in its module times the real builder, where a copy of its
    loop in this script could drift from it; the originals are restored afterwards.
    """
    originals = {name: getattr(structure_module, name) for name in WRAPPED_PARTS}
    try:
        for name, part in WRAPPED_PARTS.items():
            setattr(structure_module, name, timed(originals[name], part, seconds, calls))
        yield
    finally:
        for name, function in originals.items():
            setattr(structure_module, name, function)


def peak_rss_mib() -> float:
    """The process's peak resident set so far (Linux reports KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def proc_mib(path: str, field: str) -> float | None:
    """A "Field: N kB" line of a /proc file in MiB, None where there is none."""
    with contextlib.suppress(OSError):
        for line in Path(path).read_text().splitlines():
            if line.startswith(f"{field}:"):
                return int(line.split()[1]) / 1024
    return None


def cpu_model() -> str:
    """The processor's name from /proc/cpuinfo, else what platform knows."""
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def map_views(frames: list[Frame], count: int) -> list[Frame]:
    """`count` map views of the real frames: distinct frames spread evenly over the
    recording when there are enough, else the frames cycled, each reuse renamed
    (`name#rK`) so every view of the map is distinct."""
    if count <= len(frames):
        return [frames[int(round(i))] for i in np.linspace(0, len(frames) - 1, count)]
    views = []
    for index in range(count):
        round_number, frame = divmod(index, len(frames))
        view = frames[frame] if round_number == 0 else copy.copy(frames[frame])
        if round_number:
            view.name = f"{frames[frame].name}#r{round_number}"
        views.append(view)
    return views


def evenly_spaced(items: list, count: int) -> list:
    """`count` of `items` spread evenly over them (all of them when there are fewer)."""
    if count >= len(items):
        return list(items)
    return [items[int(round(i))] for i in np.linspace(0, len(items) - 1, count)]


def map_bytes(structure: StructureMap) -> int:
    """The map's arrays in memory (keypoints, float32 descriptors, points)."""
    return sum(
        f.keypoints.nbytes + f.descriptors.nbytes + p.nbytes
        for f, p in zip(structure.features, structure.points, strict=True)
    )


def build_and_save(
    frames: list[Frame], cameras: SceneCameras, max_features: int, path: Path
) -> tuple[StructureMap, dict]:
    """Build the map of `frames` with build_from_depth and save it, timing each part."""
    seconds = dict.fromkeys(BUILD_PARTS, 0.0)
    calls = dict.fromkeys(BUILD_PARTS, 0)
    views = TimedViews(frames, cameras, seconds)
    rss_before = peak_rss_mib()
    # CPU time beside wall time: on a shared machine the wall time also holds the
    # time other processes had the cores.
    cpu_start = time.process_time()
    start = time.perf_counter()
    with timed_build_parts(seconds, calls):
        structure = build_from_depth(views, max_features=max_features, quiet=True)
    build_total = time.perf_counter() - start
    cpu_build = time.process_time() - cpu_start
    if calls["features"] != len(frames) or calls["depth_read"] != len(frames):
        raise SystemExit(
            "build_from_depth no longer calls extract_rootsift and depth_judged once per "
            f"view ({calls}); update WRAPPED_PARTS in this benchmark"
        )
    rss_built = peak_rss_mib()
    start = time.perf_counter()
    structure.save(path)
    seconds["save"] = time.perf_counter() - start
    cpu_total = time.process_time() - cpu_start
    seconds["assembly"] = build_total - sum(seconds[p] for p in BUILD_PARTS if p != "assembly")
    seconds["depth_lifting"] = seconds["depth_read"] + seconds["lifting"]
    seconds["build_total"] = build_total
    seconds["total"] = build_total + seconds["save"]
    measured = {
        "seconds": seconds,
        "cpu_seconds": {
            "build_total": cpu_build,
            "save": cpu_total - cpu_build,
            "total": cpu_total,
        },
        "points": int(structure.point_counts().sum()),
        "keypoints": sum(len(f) for f in structure.features),
        "skipped_views": len(structure.skipped_views),
        "file_bytes": path.stat().st_size,
        "map_bytes_in_memory": map_bytes(structure),
        "peak_rss_mib": {
            "before": rss_before,
            "after_build": rss_built,
            "after_save": peak_rss_mib(),
        },
    }
    return structure, measured


def scaled(measured: dict, factor: float) -> dict:
    """Times, counts and sizes of a partial build scaled to the whole map."""
    result = dict(measured)
    for times in ("seconds", "cpu_seconds"):
        result[times] = {part: value * factor for part, value in measured[times].items()}
    for key in ("points", "keypoints", "skipped_views", "file_bytes", "map_bytes_in_memory"):
        result[key] = round(measured[key] * factor)
    return result


def memory_forecast(size: int, earlier: dict | None) -> dict | None:
    """What a build of `size` images should add to the memory in use at its peak
    (the save's temporaries dominate), from an earlier build's map bytes per image,
    and the memory the system has available."""
    if earlier is None:
        return None
    per_image = earlier["map_bytes_in_memory"] / earlier["images"]
    needed = SAVE_PEAK_FACTOR * size * per_image / MIB
    return {
        "needed_mib": needed,
        "predicted_peak_rss_mib": (proc_mib("/proc/self/status", "VmRSS") or 0.0) + needed,
        "available_mib": proc_mib("/proc/meminfo", "MemAvailable"),
    }


def check_memory(size: int, forecast: dict | None, ignore: bool) -> None:
    """Stop before a build whose save would run out of memory: the build comes first
    and takes most of the time, so an out-of-memory kill would waste all of it."""
    if not forecast or forecast["available_mib"] is None:
        return
    print(
        f"map of {size}: needs about {forecast['needed_mib']:.0f} MiB more at its peak, "
        f"{forecast['available_mib']:.0f} MiB available"
    )
    if forecast["needed_mib"] > 0.9 * forecast["available_mib"] and not ignore:
        raise SystemExit(
            f"map of {size} images would need about {forecast['needed_mib']:.0f} MiB, "
            f"{forecast['available_mib']:.0f} MiB are available: use --extrapolate-from, "
            "fewer --max-features, or --ignore-memory-forecast to try anyway"
        )


def build_row(
    size: int,
    frames: list[Frame],
    cameras: SceneCameras,
    args: argparse.Namespace,
    folder: Path,
    earlier: dict | None,
) -> tuple[StructureMap, list[Frame], dict]:
    """One map size: build (all of it, or --extrapolate-from views and scale), save.

    Returns the map, the views it was built from and the report's row.
    """
    views = map_views(frames, size)
    extrapolate = args.extrapolate_from is not None and size > args.extrapolate_from
    built_views = evenly_spaced(views, args.extrapolate_from) if extrapolate else views
    forecast = None if extrapolate else memory_forecast(size, earlier)
    check_memory(size, forecast, args.ignore_memory_forecast)
    load_before = os.getloadavg()[0]
    structure, measured = build_and_save(
        built_views, cameras, args.max_features, folder / f"map-{size}.npz"
    )
    row = scaled(measured, size / len(built_views)) if extrapolate else measured
    return (
        structure,
        built_views,
        {
            "images": size,
            "distinct_frames": min(size, len(frames)),
            "views_per_frame": math.ceil(size / len(frames)),
            "extrapolated": extrapolate,
            "measured_images": len(built_views),
            **row,
            "seconds_per_image": {p: s / size for p, s in row["seconds"].items()},
            "cpu_seconds_per_image": {p: s / size for p, s in row["cpu_seconds"].items()},
            "memory_forecast": forecast,
            "load_average_1min": {"before": load_before, "after": os.getloadavg()[0]},
        },
    )


def is_training(frame: Frame) -> bool:
    """Whether the frame is of a training sequence (1, 3, 5, 7)."""
    return frame.colour.parent.name in {f"seq-{s:02d}" for s in TRAIN_SEQUENCES}


def query_stage(
    structure: StructureMap,
    views: list[Frame],
    queries: list[Frame],
    camera: PinholeCamera,
    args: argparse.Namespace,
) -> dict:
    """Localize each query against the map; per-part times and errors."""
    candidates = [index for index, view in enumerate(views) if is_training(view)]
    thumbnails = np.stack([thumbnail(read_rgb_cv2(views[i].colour)) for i in candidates])
    errors, seconds, inliers, retrieval = [], [], [], []
    for frame in queries:
        image = read_rgb_cv2(frame.colour)
        start = time.perf_counter()
        ranked = np.argsort(-(thumbnails @ thumbnail(image)), kind="stable")
        retrieval.append(time.perf_counter() - start)
        keyframes = [candidates[i] for i in ranked[: args.keyframes].tolist()]
        answer = localize_against(
            structure, image, camera, keyframes, max_features=args.max_features
        )
        seconds.append(answer.seconds)
        inliers.append(answer.inliers)
        errors.append(pose_errors(answer.pose, frame.pose))
    return {
        "map_images": len(structure),
        "keyframe_candidates": len(candidates),
        "keyframes": args.keyframes,
        "max_features": args.max_features,
        "keyframe_choice": (
            f"retrieval stand-in: {THUMBNAIL[0]}x{THUMBNAIL[1]} grey thumbnails, cosine "
            "nearest among the map's training-sequence views (the map holds the test frames "
            "too)"
        ),
        "retrieval_median_ms": 1000 * float(np.median(retrieval)),
        **summary(errors, seconds, inliers),
    }


def build_table(builds: list[dict]) -> str:
    """The builds as a Markdown table (seconds; extrapolated rows marked)."""
    parts = (*BUILD_PARTS, "save", "total")
    lines = [
        "| images | distinct | measured | " + " | ".join(f"{p} s" for p in parts)
        + " | ms/image | CPU ms/image | points | file MiB | peak RSS MiB |",
        "|---:" * (len(parts) + 8) + "|",
    ]  # fmt: skip
    for row in builds:
        measured = f"{row['measured_images']} (extrapolated)" if row["extrapolated"] else "all"
        times = " | ".join(f"{row['seconds'][p]:.1f}" for p in parts)
        lines.append(
            f"| {row['images']} | {row['distinct_frames']} | {measured} | {times} | "
            f"{1000 * row['seconds_per_image']['total']:.1f} | "
            f"{1000 * row['cpu_seconds_per_image']['total']:.1f} | {row['points']} | "
            f"{row['file_bytes'] / MIB:.1f} | {row['peak_rss_mib']['after_save']:.0f} |"
        )
    return "\n".join(lines)


def query_table(query: dict) -> str:
    """The query stage's median times and errors as a Markdown table."""
    ms = query["median_ms"]
    position = query["median_position_m"]
    rotation = query["median_rotation_deg"]
    return "\n".join(
        [
            "| queries | map | keyframes | features ms | matching ms | solve ms | total ms "
            "| retrieval ms | failures | median error | within 5 cm / 5 deg |",
            "|---:" * 11 + "|",
            f"| {query['queries']} | {query['map_images']} | {query['keyframes']} | "
            f"{ms['features']:.1f} | {ms['matching']:.1f} | {ms['solve']:.1f} | "
            f"{ms['total']:.1f} | {query['retrieval_median_ms']:.2f} | {query['failures']} | "
            f"{'inf' if position is None else f'{100 * position:.1f} cm'} / "
            f"{'inf' if rotation is None else f'{rotation:.2f} deg'} | "
            f"{query['within_5cm_5deg']:.1%} |",
        ]
    )


def parse_arguments() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("/work/shared/data/7scenes-redkitchen"))
    parser.add_argument("--scene", default="redkitchen")
    parser.add_argument("--map-sizes", type=int, nargs="+", default=[700, 10_000])
    parser.add_argument(
        "--real-frames", type=int, help="use this many of the real frames (default: all)"
    )
    parser.add_argument("--extrapolate-from", type=int, metavar="N")
    parser.add_argument(
        "--ignore-memory-forecast",
        action="store_true",
        help="build even when the forecast says the save will not fit in memory",
    )
    parser.add_argument("--max-features", type=int, default=1024)
    parser.add_argument("--queries", type=int, default=30, help="0: no query stage")
    parser.add_argument("--keyframes", type=int, default=10)
    parser.add_argument("--threads", type=int, default=1, help="torch and OpenCV threads")
    parser.add_argument("--map-dir", type=Path, help="where map files go (default: a temp dir)")
    parser.add_argument(
        "--out", type=Path, default=Path("benchmarks/results/structure_build_cost.json")
    )
    args = parser.parse_args()
    numbers = [*args.map_sizes, args.max_features, args.keyframes, args.threads]
    numbers += [n for n in (args.real_frames, args.extrapolate_from) if n is not None]
    if min(numbers) < 1 or args.queries < 0:
        parser.error("sizes, counts and --threads must be at least 1 (--queries at least 0)")
    args.map_sizes = sorted(set(args.map_sizes))  # ascending: see the docstring on memory
    return args


def query_map_size(args: argparse.Namespace, real_frames: int) -> int | None:
    """The map the queries use: the largest of --map-sizes without repeated views."""
    if args.queries == 0:
        return None
    distinct = [size for size in args.map_sizes if size <= real_frames]
    if not distinct:
        raise SystemExit(f"the query stage needs a map size of at most {real_frames} frames")
    return max(distinct)


def main() -> None:
    args = parse_arguments()
    set_threads(args.threads)
    scene = args.data / args.scene
    if not scene.is_dir():
        raise SystemExit(f"no scene folder {scene}")
    frames = frames_of(scene, ALL_SEQUENCES)
    # The loader's cameras: colour 525 for keypoints, depth 585 registered onto it.
    cameras = scene_cameras(scene, [frame.colour for frame in frames], intrinsics_for="depth")
    if args.real_frames is not None:
        frames = evenly_spaced(frames, args.real_frames)
    query_size = query_map_size(args, len(frames))
    report: dict = {
        "complete": False,
        "command": sys.argv,
        "data": str(scene),
        "real_frames": len(frames),
        "repeated_views": REPEATS_NOTE,
        "max_features": args.max_features,
        "machine": cpu_model(),
        "cores": os.cpu_count(),
        "threads": args.threads,
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
        "versions": {
            "python": platform.python_version(),
            "opencv": cv2.__version__,
            "poselib": poselib.__version__,
            "numpy": np.__version__,
            "torch": torch.__version__,
        },
        "load_average_1min": {"before": os.getloadavg()[0], "after": None},
        "builds": [],
        "query": None,
    }
    with contextlib.ExitStack() as stack:
        folder = args.map_dir or Path(stack.enter_context(tempfile.TemporaryDirectory()))
        folder.mkdir(parents=True, exist_ok=True)
        for size in args.map_sizes:
            earlier = report["builds"][-1] if report["builds"] else None
            structure, views, row = build_row(size, frames, cameras, args, folder, earlier)
            report["builds"].append(row)
            marked = " (extrapolated)" if row["extrapolated"] else ""
            print(f"map of {size}: {row['seconds']['total']:.1f} s{marked}")
            if size == query_size:
                queries = evenly_spaced(frames_of(scene, TEST_SEQUENCES), args.queries)
                report["query"] = query_stage(structure, views, queries, cameras.colour, args)
            del structure
            gc.collect()  # free this map before the next, larger one is built
            write_json(report, args.out)
    report["load_average_1min"]["after"] = os.getloadavg()[0]
    report["complete"] = True
    load = report["load_average_1min"]
    print(
        f"\n{args.scene}, {len(frames)} real frames, {args.threads} thread(s), "
        f"{os.cpu_count()} cores, load average {load['before']:.1f} before, "
        f"{load['after']:.1f} after\n"
    )
    print(build_table(report["builds"]))
    if report["query"] is not None:
        print()
        print(query_table(report["query"]))
    write_json(report, args.out)


if __name__ == "__main__":
    main()
