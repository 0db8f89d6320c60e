"""How the structure-based refiner grows with the map: 400 to 10^5 images.

Method.
1. Build, measured: relocfw.structure.build_from_depth (RootSIFT, depth registered
   and lifted) on --build-frames distinct Red Kitchen training frames (sequences 1, 3,
   5, 7; 400 by default, all of them), once per mode: one worker with one OpenCV
   thread, one worker with --opencv-threads OpenCV threads, and a process pool of each
   of --workers (one thread per worker; the frames in small tasks, the parts merged in
   order). SIFT runs at --image-scale of each side (0.5, refine=features' default;
   queries too). Each mode's map must equal the first's (`same_map_as_first`). Build time at
   a larger size is extrapolated from the images per second (every image is built
   alone, so the cost is linear): such rows list "build" under `extrapolated`.
2. Today's layout at the built size, measured: the StructureMap's arrays in memory
   (float32 descriptors), its npz file, StructureMap.save and .load. Above it these
   are extrapolated per image (a 10^5 map would need about 40 GB of memory).
3. The compact layout (relocfw.structure.compact_map: flat .npy arrays opened
   memory-mapped, only keypoints with a 3-D point, points in float16 camera frames,
   descriptors as the uint8 grid or product-quantised, relocfw.structure.
   descriptor_codes) at the built size for each of --codes (bytes per descriptor:
   128 = the grid, less = PQ trained on the map), queried with the same keyframes as
   the in-memory map: the accuracy cost of each code.
4. Growing maps, measured at every size: copies of the built map, copy c a rigid
   transform of the scene (a random rotation, and a place on a grid 30 m apart), its
   poses moved and its camera-frame points with them, names `<frame>#c<c>`; written
   with --scale-code by the streaming CompactMapWriter (timed), opened (timed),
   bytes per image on disk and held in memory, resident memory.
   Retrieval: each map image has a global descriptor of --retrieval-dim: the real
   16 x 12 grey thumbnail of its frame (structure_query.py's retrieval stand-in) and
   a random signature of its copy (a stand-in for what tells one room of a building
   from another). A query is placed in a random copy (its ground truth moved with
   it) and carries that copy's signature, so retrieval searches every image and must
   find the right copy. Timed per query: today's keyframes_by_descriptor (numpy,
   z-scored, exhaustive) and plugins/faiss_index.py for each of --faiss-kinds
   (`kind` or `kind:precision`, e.g. flat:float16)
   (recall: the share of the exhaustive keyframes found).
   Query: the first faiss kind's keyframes; the map's file pages are evicted from
   the page cache (posix_fadvise), the map opened, the keyframes read from disk
   (cold) and again (warm), then localize_against on them (RootSIFT of the query,
   matching, PoseLib). Errors against the moved ground truth: a wrong copy is metres
   off, so the errors show the answers stay right. Totals per retrieval method:
   that method's retrieval ms plus the same reads and solves; also without the
   query's own SIFT extraction, the one part no map size changes.
The issue's targets (`done_when`): query ms with faiss retrieval grows by less than
2x from the smallest size to the largest, and at most 20 KB per map image on disk.

Writes JSON after every stage (`complete` false until the end) and prints tables.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/structure_scale.py \\
        --sizes 400 2000 10000 100000 --threads 1
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import math
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from common import write_json  # benchmarks/, the script's own folder
from scale_maps import (
    THUMBNAIL_DIMENSIONS,
    base_rows,
    copy_transform,
    evict_from_cache,
    map_descriptors,
    placed,
    query_descriptor,
    timed_build,
    write_copies,
)
from structure_build_cost import cpu_model, evenly_spaced, map_bytes, peak_rss_mib, proc_mib
from structure_query import (
    TEST_SEQUENCES,
    TRAIN_SEQUENCES,
    WITHIN_DEG,
    WITHIN_M,
    finite_or_none,
    frames_of,
    pose_errors,
    read_rgb_cv2,
    set_threads,
    thumbnail,
)

from relocfw.core.standardise import ROWS_AT_A_TIME, ZScore
from relocfw.data.sevenscenes import scene_cameras
from relocfw.plugins.faiss_index import KINDS, PRECISIONS, FaissIndex, import_faiss
from relocfw.structure import StructureMap, localize_against
from relocfw.structure.compact_map import CompactMap
from relocfw.structure.compact_writer import lock_file
from relocfw.structure.descriptor_codes import codec_of_bytes
from relocfw.structure.refiner_inputs import keyframes_by_descriptor

TARGET_BYTES_PER_IMAGE = 20_000
TARGET_QUERY_GROWTH = 2.0
MAPPED_FILES = ("codes.npy", "points.npy")


def rss_mib() -> float | None:
    return proc_mib("/proc/self/status", "VmRSS")


def npz_stage(structure: StructureMap, folder: Path) -> dict:
    """Today's layout: bytes in memory, the npz file, save and load."""
    path = folder / "map.npz"
    start = time.perf_counter()
    structure.save(path)
    saved = time.perf_counter() - start
    start = time.perf_counter()
    loaded = StructureMap.load(path)
    load = time.perf_counter() - start
    del loaded
    count = len(structure)
    return {
        "images": count,
        "memory_bytes_per_image": map_bytes(structure) / count,
        "file_bytes_per_image": path.stat().st_size / count,
        "save_s": saved,
        "load_s": load,
        "points_per_image": float(structure.point_counts().mean()),
        "keypoints_per_image": sum(len(f) for f in structure.features) / count,
    }


def accuracy(errors: list[tuple[float, float]], inliers: list[int]) -> dict:
    """Median errors (a failure is infinitely wrong), failures, the 5 cm / 5 deg share."""
    position = np.array([e[0] for e in errors])
    rotation = np.array([e[1] for e in errors])
    return {
        "queries": len(errors),
        "failures": int(np.isinf(position).sum()),
        "median_position_m": finite_or_none(float(np.median(position))),
        "median_rotation_deg": finite_or_none(float(np.median(rotation))),
        "within_5cm_5deg": float(np.mean((position <= WITHIN_M) & (rotation <= WITHIN_DEG))),
        "median_inliers": float(np.median(inliers)),
    }


def medians_ms(seconds: list[dict]) -> dict:
    return {part: 1000 * float(np.median([s[part] for s in seconds])) for part in seconds[0]}


def reference_queries(structure, queries, images, keyframes, camera, args) -> dict:
    """Queries against the in-memory StructureMap (every keypoint, float32)."""
    errors, inliers, seconds = [], [], []
    for frame, image, chosen in zip(queries, images, keyframes, strict=True):
        answer = localize_against(
            structure,
            image,
            camera,
            chosen,
            max_features=args.max_features,
            image_scale=args.image_scale,
        )
        errors.append(pose_errors(answer.pose, frame.pose))
        inliers.append(answer.inliers)
        seconds.append(answer.seconds)
    return {**accuracy(errors, inliers), "median_ms": medians_ms(seconds)}


def compact_queries(
    folder: Path, queries: list, images: list, keyframes: list, copies: list, camera, args
) -> tuple[dict, list[dict]]:
    """Each query against the compact map in `folder`: its pages evicted, the map
    opened, the keyframes read cold and again warm, localize_against; errors against
    the query's ground truth moved into its copy. Returns the summary and each
    query's seconds."""
    errors, inliers, seconds = [], [], []
    rss_open = None
    for frame, image, chosen, copy in zip(queries, images, keyframes, copies, strict=True):
        # The previous query's map was deleted (unmapped): its pages can be evicted.
        evict_from_cache([folder / name for name in MAPPED_FILES])
        start = time.perf_counter()
        compact = CompactMap.open(folder)
        opened = time.perf_counter()
        compact.keyframe_map(chosen)
        cold = time.perf_counter()
        keyframe_map = compact.keyframe_map(chosen)
        warm = time.perf_counter()
        rss_open = rss_open or rss_mib()
        answer = localize_against(
            keyframe_map,
            image,
            camera,
            list(range(len(chosen))),
            max_features=args.max_features,
            image_scale=args.image_scale,
        )
        errors.append(
            pose_errors(answer.pose, placed(frame.pose, *copy_transform(copy, args.seed)))
        )
        inliers.append(answer.inliers)
        parts = {"open": opened - start, "cold_fetch": cold - opened, "warm_fetch": warm - cold}
        seconds.append({**parts, **answer.seconds})
        del compact, keyframe_map
    summary = {**accuracy(errors, inliers), "median_ms": medians_ms(seconds)}
    return {**summary, "rss_mib_with_map_open": rss_open}, seconds


def standardised(zscore: ZScore, descriptors: np.ndarray) -> np.ndarray:
    """zscore(descriptors) in float64, chunk by chunk (no float64 temporary of all)."""
    out = np.empty(descriptors.shape, dtype=np.float64)
    for start in range(0, len(descriptors), ROWS_AT_A_TIME):
        out[start : start + ROWS_AT_A_TIME] = zscore(descriptors[start : start + ROWS_AT_A_TIME])
    return out


def timed_queries(search, asked: list[np.ndarray]) -> tuple[list[list[int]], list[float]]:
    """Each query's keyframes by `search` and the seconds each took."""
    found, seconds = [], []
    for descriptor in asked:
        start = time.perf_counter()
        found.append(search(descriptor))
        seconds.append(time.perf_counter() - start)
    return found, seconds


def faiss_spec(spec: str) -> tuple[str, str]:
    """--faiss-kinds' entry as (kind, precision): "flat", "ivf", "flat:float16" (the
    descriptors stored as float16: half the bytes to read, still an exhaustive search)."""
    kind, _, precision = spec.partition(":")
    return kind, precision or "float32"


def retrieval_stage(
    descriptors: np.ndarray, asked: list[np.ndarray], kinds: list[str], args
) -> tuple[dict, dict[str, list[list[int]]], dict[str, list[float]]]:
    """Keyframes of each query: today's exhaustive numpy search, then each faiss kind.

    Returns the rows, and per method each query's keyframes and seconds.
    """
    start = time.perf_counter()
    zscore = ZScore().fit(descriptors)
    points = standardised(zscore, descriptors)
    fit = time.perf_counter() - start
    exact, seconds = timed_queries(
        lambda d, points=points: keyframes_by_descriptor(zscore, points, d, args.keyframes), asked
    )
    rows = {"exhaustive numpy": {"fit_s": fit, "median_ms": 1000 * float(np.median(seconds))}}
    keyframes, times = {"exhaustive numpy": exact}, {"exhaustive numpy": seconds}
    del points
    gc.collect()
    count = min(args.keyframes, len(descriptors))  # faiss refuses more than the map has
    for spec in kinds:
        kind, precision = faiss_spec(spec)
        nlist = max(1, round(len(descriptors) ** 0.5))
        index = FaissIndex(
            kind=kind, precision=precision, nlist=nlist, nprobe=min(args.nprobe, nlist)
        )
        start = time.perf_counter()
        index.fit(descriptors)
        fit = time.perf_counter() - start
        found, seconds = timed_queries(
            lambda d, index=index: index.neighbours(d[None], count)[1][0].tolist(), asked
        )
        shared = [len(set(f) & set(e)) / len(e) for f, e in zip(found, exact, strict=True)]
        rows[f"faiss {spec}"] = {
            "fit_s": fit,
            "median_ms": 1000 * float(np.median(seconds)),
            "recall_of_exhaustive_keyframes": float(np.mean(shared)),
        }
        if kind == "ivf":
            rows[f"faiss {spec}"].update(nlist=nlist, nprobe=min(args.nprobe, nlist))
        keyframes[f"faiss {spec}"], times[f"faiss {spec}"] = found, seconds
        del index
        gc.collect()
    return rows, keyframes, times


def build_stage(frames: list, cameras, args, report: dict) -> StructureMap:
    """The real build in every mode; the first mode's map is kept."""
    modes = [(1, 1)]
    if args.opencv_threads > 1:
        modes.append((1, args.opencv_threads))
    modes += [(workers, 1) for workers in args.workers if workers > 1]
    structure = None
    for workers, threads in modes:
        built, row = timed_build(
            frames, cameras, args.max_features, workers, threads, args.image_scale
        )
        if structure is None:
            structure = built
        else:
            row["same_map_as_first"] = built.same_as(structure)
        row["speed_up"] = (
            report["builds"][0]["seconds"] / row["seconds"] if report["builds"] else 1.0
        )
        report["builds"].append(row)
        print(f"build, {workers} worker(s), {threads} OpenCV thread(s): {row['seconds']:.1f} s")
        del built
        gc.collect()
    set_threads(args.threads)
    return structure


def remove_compact_map(folder: Path) -> None:
    """Remove a compact map: its folder is a link to the version a writer published
    (relocfw.structure.compact_writer), so both go, with the writers' lock file."""
    version = folder.resolve()
    if folder.is_symlink():
        folder.unlink()
    shutil.rmtree(version)
    lock_file(folder).unlink(missing_ok=True)


def code_stage(structure, rows_of, codecs, folder, queries, images, keyframes, camera, args):
    """The built map in the compact layout under each code, queried with `keyframes`
    (the accuracy cost of each code against the in-memory map)."""
    results = []
    for code_bytes, codec in codecs.items():
        target = folder / f"compact-{code_bytes}"
        rows = rows_of[code_bytes]
        seconds = write_copies(target, structure, rows, codec, len(structure), args.point_dtype, 0)
        disk = CompactMap.open(target).file_bytes()
        copies = [0] * len(queries)
        answered, _ = compact_queries(target, queries, images, keyframes, copies, camera, args)
        results.append(
            {
                "code_bytes": code_bytes,
                "code": codec.kind,
                "point_dtype": args.point_dtype,
                "write_s": seconds,
                "disk_bytes_per_image": disk / len(structure),
                **answered,
            }
        )
        remove_compact_map(target)
        print(f"code {code_bytes} B: {disk / len(structure) / 1000:.1f} KB/image", flush=True)
    return results


def query_totals(retrieval: list[float], seconds: list[dict]) -> dict:
    """Median ms of a whole query: retrieval, then the keyframes read warm (the map's
    pages cached) or cold (evicted, the map opened), then features, matching, solve."""
    local = [s["features"] + s["matching"] + s["solve"] for s in seconds]
    warm = [r + s["warm_fetch"] + m for r, s, m in zip(retrieval, seconds, local, strict=True)]
    cold = [
        r + s["open"] + s["cold_fetch"] + m
        for r, s, m in zip(retrieval, seconds, local, strict=True)
    ]
    # What a map's size can change: all but the query's own SIFT extraction, which
    # on a shared machine varies more than the rest of the query.
    mapped = [
        r + s["warm_fetch"] + s["matching"] + s["solve"]
        for r, s in zip(retrieval, seconds, strict=True)
    ]
    return {
        "warm": 1000 * float(np.median(warm)),
        "cold": 1000 * float(np.median(cold)),
        "warm_without_query_features": 1000 * float(np.median(mapped)),
    }


def scale_row(size: int, inputs: dict, report: dict, folder: Path, args) -> dict:
    """One map size: write the copies, open, retrieve, query."""
    structure, codec = inputs["structure"], inputs["codec"]
    base = len(structure)
    target = folder / f"scale-{size}"
    write_s = write_copies(
        target, structure, inputs["rows"], codec, size, args.point_dtype, args.seed
    )
    rss_before = rss_mib()
    start = time.perf_counter()
    compact = CompactMap.open(target)
    open_s = time.perf_counter() - start
    disk, resident = compact.file_bytes(), compact.resident_bytes()
    del compact
    full_copies = max(1, size // base)
    copies = np.random.default_rng([args.seed, size]).integers(full_copies, size=args.queries)
    copies = copies[: len(inputs["queries"])].tolist()
    asked = [
        query_descriptor(image, copy, args.retrieval_dim, args.seed)
        for image, copy in zip(inputs["images"], copies, strict=True)
    ]
    descriptors = map_descriptors(inputs["thumbnails"], size, args.retrieval_dim, args.seed)
    retrieval, keyframes, retrieval_s = retrieval_stage(descriptors, asked, args.faiss_kinds, args)
    method = query_method(args)
    del descriptors
    gc.collect()
    answered, seconds = compact_queries(
        target,
        inputs["queries"],
        inputs["images"],
        keyframes[method],
        copies,
        inputs["camera"],
        args,
    )
    builds, npz = report["builds"], report["npz"]
    fastest = max(builds, key=lambda b: b["images_per_second"])
    factor = size / npz["images"]
    return {
        "map_images": size,
        "copies": -(-size // base),
        "measured": ["write_s", "open_s", "disk_bytes_per_image", "resident_bytes_per_image",
                     "rss_mib", "retrieval", "query"],
        "extrapolated": ["build", "in_memory_layout"] if size > base else [],
        "build": {
            "one_worker_s": size / builds[0]["images_per_second"],
            "fastest_s": size / fastest["images_per_second"],
            "fastest_mode": {key: fastest[key] for key in ("workers", "opencv_threads")},
        },
        "in_memory_layout": {
            "memory_bytes": npz["memory_bytes_per_image"] * size,
            "npz_file_bytes": npz["file_bytes_per_image"] * size,
            "npz_load_s": npz["load_s"] * factor,
        },
        "write_s": write_s,
        "open_s": open_s,
        "disk_bytes_per_image": disk / size,
        "resident_bytes_per_image": resident / size,
        "rss_mib": {"before_open": rss_before,
                    "with_map_open": answered.pop("rss_mib_with_map_open")},
        "retrieval": retrieval,
        "query_retrieval": method,
        "query": {
            **answered,
            # Every method's retrieval time with the same reads and solves (those of
            # `query_retrieval`'s keyframes; recall says how far another's differ).
            "median_total_ms": {m: query_totals(retrieval_s[m], seconds) for m in retrieval_s},
        },
    }  # fmt: skip


def query_method(args: argparse.Namespace) -> str:
    """The retrieval whose keyframes the query stage uses."""
    return f"faiss {args.faiss_kinds[0]}" if args.faiss_kinds else "exhaustive numpy"


def done_when(rows: list[dict]) -> dict:
    """The issue's two targets, between the smallest and the largest size: query ms
    growth for each retrieval method (warm and cold reads, and warm without the query's
    SIFT), and disk bytes per image. `query_growth_met` is the query stage's own
    method's (the first faiss kind), warm and cold."""
    first, last = rows[0], rows[-1]
    growth = {
        method: {
            read: last["query"]["median_total_ms"][method][read] / ms
            for read, ms in first["query"]["median_total_ms"][method].items()
        }
        for method in first["query"]["median_total_ms"]
    }
    chosen = growth[last["query_retrieval"]]
    return {
        "from_images": first["map_images"],
        "to_images": last["map_images"],
        "query_retrieval": last["query_retrieval"],
        "query_ms_growth": growth,
        "query_growth_met": chosen["warm"] < TARGET_QUERY_GROWTH
        and chosen["cold"] < TARGET_QUERY_GROWTH,
        "disk_bytes_per_image": last["disk_bytes_per_image"],
        "bytes_met": last["disk_bytes_per_image"] <= TARGET_BYTES_PER_IMAGE,
    }


def error_text(metres: float | None) -> str:
    return "inf" if metres is None else f"{100 * metres:.1f} cm"


def tables(report: dict) -> str:
    """The report's main numbers as Markdown tables."""
    lines = ["| build | images | s | images/s | speed-up |", "|---|---:|---:|---:|---:|"]
    for b in report["builds"]:
        lines.append(
            f"| {b['workers']} worker(s), {b['opencv_threads']} OpenCV thread(s) | {b['images']} "
            f"| {b['seconds']:.1f} | {b['images_per_second']:.2f} | {b['speed_up']:.2f} |"
        )
    lines += ["", "| map layout | B/desc | KB/image | median error | fail | 5cm5deg | match ms |",
              "|---|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    entries = [
        ("StructureMap npz", 128, report["npz"]["file_bytes_per_image"], report["reference"])
    ]
    entries += [(f"compact {c['code']}", c["code_bytes"], c["disk_bytes_per_image"], c)
                for c in report["codes"]]  # fmt: skip
    for name, code, size, r in entries:
        lines.append(
            f"| {name} | {code} | {size / 1000:.1f} | {error_text(r['median_position_m'])} | "
            f"{r['failures']} | {r['within_5cm_5deg']:.0%} | {r['median_ms']['matching']:.1f} |"
        )
    lines += ["", "| images | write s | open ms | KB/image | exhaustive ms | faiss ms | "
              "query ms warm | cold | median error | fail |", "|---:" * 10 + "|"]  # fmt: skip
    for row in report["rows"]:
        query = row["query"]
        totals = query["median_total_ms"][row["query_retrieval"]]
        lines.append(
            f"| {row['map_images']} | {row['write_s']:.1f} | {1000 * row['open_s']:.1f} | "
            f"{row['disk_bytes_per_image'] / 1000:.1f} | "
            f"{row['retrieval']['exhaustive numpy']['median_ms']:.1f} | "
            f"{row['retrieval'].get(row['query_retrieval'], {}).get('median_ms', math.nan):.1f} | "
            f"{totals['warm']:.1f} | {totals['cold']:.1f} | "
            f"{error_text(query['median_position_m'])} | {query['failures']} |"
        )
    return "\n".join(lines)


def parse_arguments() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("/work/shared/data/7scenes-redkitchen"))
    parser.add_argument("--scene", default="redkitchen")
    parser.add_argument("--sizes", type=int, nargs="+", default=[400, 2000, 10_000, 100_000])
    parser.add_argument("--build-frames", type=int, default=400, help="real frames built")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, os.cpu_count() or 1])
    parser.add_argument(
        "--opencv-threads",
        type=int,
        default=os.cpu_count() or 1,
        help="a one-worker build with this many OpenCV threads (<= 1: none)",
    )
    parser.add_argument("--max-features", type=int, default=1024)
    parser.add_argument(
        "--image-scale", type=float, default=0.5, help="SIFT's share of each side (refine's)"
    )
    parser.add_argument("--queries", type=int, default=30)
    parser.add_argument("--keyframes", type=int, default=10)
    parser.add_argument(
        "--codes",
        type=int,
        nargs="+",
        default=[128, 32, 16, 8],
        help="bytes per descriptor compared (128: uint8 grid, less: PQ)",
    )
    parser.add_argument("--scale-code", type=int, default=16, help="bytes per descriptor")
    parser.add_argument("--point-dtype", choices=("float16", "float32"), default="float16")
    parser.add_argument("--retrieval-dim", type=int, default=2048)
    parser.add_argument("--faiss-kinds", nargs="*", default=["flat", "ivf"])
    parser.add_argument("--nprobe", type=int, default=16)
    parser.add_argument("--threads", type=int, default=1, help="torch, OpenCV, faiss threads")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--map-dir", type=Path, help="where maps go (default: a temp dir)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/structure_scale.json"))
    args = parser.parse_args()
    numbers = [*args.sizes, *args.workers, args.build_frames, args.queries, args.keyframes]
    if min([*numbers, args.threads, args.max_features]) < 1:
        parser.error("sizes, counts, workers and --threads must be at least 1")
    if args.retrieval_dim <= THUMBNAIL_DIMENSIONS:
        parser.error(f"--retrieval-dim must exceed the {THUMBNAIL_DIMENSIONS}-d thumbnail")
    for spec in args.faiss_kinds:
        kind, precision = faiss_spec(spec)
        if kind not in KINDS or precision not in PRECISIONS:
            parser.error(
                f"--faiss-kinds {spec!r}: give kind[:precision], kind one of {KINDS}, "
                f"precision one of {PRECISIONS}"
            )
    args.sizes = sorted(set(args.sizes))
    args.codes = list(dict.fromkeys([*args.codes, args.scale_code]))
    return args


def new_report(args: argparse.Namespace, scene: Path, frames: list, queries: list) -> dict:
    return {
        "complete": False,
        "command": sys.argv,
        "data": str(scene),
        "machine": cpu_model(),
        "cores": os.cpu_count(),
        "threads": args.threads,
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
        "versions": {"python": platform.python_version(), "opencv": cv2.__version__},
        "built_frames": len(frames),
        "queries": len(queries),
        "keyframes": args.keyframes,
        "max_features": args.max_features,
        "image_scale": args.image_scale,
        "point_dtype": args.point_dtype,
        "scale_code_bytes": args.scale_code,
        "retrieval_descriptors": (
            f"{args.retrieval_dim}-d: the real {THUMBNAIL_DIMENSIONS}-d grey thumbnail of the "
            "frame, then a random signature of its copy; a query carries its copy's"
        ),
        "builds": [],
    }


def main() -> None:
    args = parse_arguments()
    set_threads(args.threads)
    import_faiss().omp_set_num_threads(args.threads)
    scene = args.data / args.scene
    if not scene.is_dir():
        raise SystemExit(f"no scene folder {scene}")
    training = frames_of(scene, TRAIN_SEQUENCES)
    frames = evenly_spaced(training, args.build_frames)
    # The loader's cameras: colour 525 for keypoints, depth 585 registered onto it.
    cameras = scene_cameras(scene, [f.colour for f in training], intrinsics_for="depth")
    queries = evenly_spaced(frames_of(scene, TEST_SEQUENCES), args.queries)
    images = [read_rgb_cv2(q.colour) for q in queries]
    report = new_report(args, scene, frames, queries)
    with contextlib.ExitStack() as stack:
        folder = args.map_dir or Path(stack.enter_context(tempfile.TemporaryDirectory()))
        folder.mkdir(parents=True, exist_ok=True)
        structure = build_stage(frames, cameras, args, report)
        report["npz"] = npz_stage(structure, folder)
        write_json(report, args.out)
        thumbnails = np.stack([thumbnail(read_rgb_cv2(f.colour)) for f in frames])
        # The built map alone (copy 0): exact keyframes, the same for every layout.
        descriptors = map_descriptors(thumbnails, len(frames), args.retrieval_dim, args.seed)
        asked = [query_descriptor(image, 0, args.retrieval_dim, args.seed) for image in images]
        exact = retrieval_stage(descriptors, asked, [], args)[1]["exhaustive numpy"]
        camera = cameras.colour
        report["reference"] = {
            "map": "StructureMap in memory: every keypoint, float32 descriptors on the uint8 grid",
            **reference_queries(structure, queries, images, exact, camera, args),
        }
        stored = np.concatenate(
            [
                features.descriptors[np.isfinite(points).all(axis=1)]
                for features, points in zip(structure.features, structure.points, strict=True)
            ]
        )
        codecs = {code: codec_of_bytes(code, stored, args.seed) for code in args.codes}
        rows_of = {code: base_rows(structure, codec) for code, codec in codecs.items()}
        report["codes"] = code_stage(
            structure, rows_of, codecs, folder, queries, images, exact, camera, args
        )
        write_json(report, args.out)
        inputs = {
            "structure": structure,
            "codec": codecs[args.scale_code],
            "rows": rows_of[args.scale_code],
            "thumbnails": thumbnails,
            "queries": queries,
            "images": images,
            "camera": camera,
        }
        report["rows"] = []
        for size in args.sizes:
            row = scale_row(size, inputs, report, folder, args)
            report["rows"].append(row)
            report["done_when"] = done_when(report["rows"])
            report["peak_rss_mib"] = peak_rss_mib()
            write_json(report, args.out)
            remove_compact_map(folder / f"scale-{size}")
            totals = row["query"]["median_total_ms"][row["query_retrieval"]]
            print(f"map of {size}: {totals['warm']:.0f} ms a query (warm)", flush=True)
    report["complete"] = True
    print(tables(report))
    print(report["done_when"])
    write_json(report, args.out)


if __name__ == "__main__":
    main()
