"""RGB-only map and solver settings on a validation block, with oracle retrieval.

refine=features_rgb triangulates its map between map images with their known poses
and the colour camera, then solves each query by PnP against the keyframes'
points. This measures its settings one variant at a time on a VALIDATION block of
the training sequences (map: --map-sequences, default 1, 3 and 5; queries:
--query-sequence, default 7; never the test split), with everything but the
variant's own keys at refine=features_rgb's defaults. Per variant:

- the map's points against registered depth (relocfw.structure.map_quality): share
  of keypoints with a point, median error and median ratio of triangulated to depth
  range;
- the queries, each matched against the `keyframes` map images nearest its
  ground-truth pose (an oracle retrieval, so variants compare maps and solvers, not
  retrieval): median errors, share within 5 cm / 5 deg, failures, and each query's
  errors (for paired tests between variants).

A variant is NAME:key=value,key=value with keys from: focal (the colour camera's focal
length, pixels: 7-Scenes gives only the depth sensor's, 585; 525 is the community's
nominal colour value), max_features, image_scale, keyframes, max_error_px,
min_inliers, and any triangulation setting (partners, min_partner_angle_deg,
max_partner_angle_deg, epipolar_px, max_reprojection_px, min_views, min_angle_deg,
ratio), and two experiments the library has no option for: within_recording=1
(partners only from the map image's own recording, the folder part of its name; see
`partners_within_recording`) and loss_px (the scale, pixels, of the Cauchy loss of
PoseLib's final refinement over the inliers; 0 keeps PoseLib's own, half the inlier
bound; see `poselib_loss_scale`).

    OMP_NUM_THREADS=2 .venv/bin/python -m benchmarks.rgb_settings_oracle \
        --variant default: --variant f532:focal=532 --out benchmarks/results/x.json
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import platform
import time
from pathlib import Path

import numpy as np

import relocfw.structure.tracks as tracks_module
from benchmarks.common import write_json
from benchmarks.rgb_map_quality import LazyViews, query_errors
from relocfw.core.camera import PinholeCamera
from relocfw.data.frames import Frame
from relocfw.data.sevenscenes import load_sevenscenes
from relocfw.plugins.sequence_refiner import recording_of
from relocfw.structure import build_by_triangulation
from relocfw.structure.covisibility import scene_depths
from relocfw.structure.map_quality import depth_agreement, point_share
from relocfw.structure.tracks import TrackSettings

ROOT = Path("/work/shared/data/7scenes-redkitchen")
# refine=features_rgb's defaults (conf/refine/features.yaml and features_rgb.yaml);
# focal None keeps the loader's colour camera.
DEFAULTS: dict[str, float | int | None] = {
    "focal": None,
    "max_features": 1024,
    "image_scale": 0.5,
    "keyframes": 20,
    "max_error_px": 16.0,
    "min_inliers": 8,
    "within_recording": 0,
    "loss_px": 0.0,
}
TRIANGULATION_DEFAULTS: dict[str, float | int] = {"epipolar_px": 6.0, "max_reprojection_px": 6.0}
TRIANGULATION_KEYS = (
    "partners",
    "min_partner_angle_deg",
    "max_partner_angle_deg",
    "epipolar_px",
    "max_reprojection_px",
    "min_views",
    "min_angle_deg",
    "ratio",
)
INTEGER_KEYS = (
    "max_features",
    "keyframes",
    "min_inliers",
    "partners",
    "min_views",
    "within_recording",
)
WITHIN_M, WITHIN_DEG = 0.05, 5.0


@dataclasses.dataclass
class Variant:
    name: str
    settings: dict
    triangulation: dict


def parsed_variant(text: str) -> Variant:
    """NAME:key=value,... as a Variant over the defaults; an unknown key exits naming it."""
    name, _, rest = text.partition(":")
    settings, triangulation = dict(DEFAULTS), dict(TRIANGULATION_DEFAULTS)
    for item in filter(None, rest.split(",")):
        key, _, value = item.partition("=")
        number = int(value) if key in INTEGER_KEYS else float(value)
        if key in DEFAULTS:
            settings[key] = number
        elif key in TRIANGULATION_KEYS:
            triangulation[key] = number
        else:
            raise SystemExit(f"--variant {text}: unknown key {key!r}")
    return Variant(name or text, settings, triangulation)


def with_focal(frames: list[Frame], focal: float | None) -> list[Frame]:
    """The frames with the colour camera's focal length replaced (principal point kept)."""
    if focal is None:
        return frames
    out = []
    for frame in frames:
        camera = frame.camera
        changed = PinholeCamera(focal, focal, camera.cx, camera.cy, camera.width, camera.height)
        out.append(dataclasses.replace(frame, camera=changed))
    return out


@contextlib.contextmanager
def partners_within_recording(names: list[str], enabled: bool):
    """While open (and `enabled`), the map build takes each image's partners only
    among images of its own recording, in the library's own order of preference.

    The hypothesis it tests: 7-Scenes' recordings disagree with each other by a few
    cm (benchmarks/block_consistency.py), so a track spanning two recordings might
    hold a point right for neither. The library chooses partners by geometry alone
    and has no option for this; the benchmark swaps the partner choice of
    relocfw.structure.tracks for the duration of one build and restores it.
    """
    if not enabled:
        yield
        return
    recordings = [recording_of(name) for name in names]
    library_choice = tracks_module.covisible_partners

    def within(poses, cameras, depths, partners, min_angle_deg, max_angle_deg):
        if len(poses) != len(recordings):
            raise ValueError(f"{len(poses)} poses but {len(recordings)} map image names")
        every = library_choice(poses, cameras, depths, len(poses), min_angle_deg, max_angle_deg)
        return [
            [j for j in row if recordings[j] == recordings[i]][:partners]
            for i, row in enumerate(every)
        ]

    tracks_module.covisible_partners = within
    try:
        yield
    finally:
        tracks_module.covisible_partners = library_choice


@contextlib.contextmanager
def poselib_loss_scale(pixels: float):
    """While open (and `pixels` > 0), PoseLib's absolute-pose solves refine their
    inliers with a Cauchy loss of this scale instead of PoseLib's own (half the RANSAC
    inlier bound: 8 px under refine=features_rgb's 16 px bound).

    The hypothesis it tests: a wide inlier bound keeps queries from failing, and a
    tighter loss in the final refinement might weigh the precise correspondences
    more. relocfw.structure.absolute_pose imports poselib when it solves, so the
    module's function is swapped for the duration and restored.
    """
    if pixels <= 0:
        yield
        return
    import poselib

    library_solve = poselib.estimate_absolute_pose

    def with_loss(points_2d, points_3d, camera, ransac, bundle):
        return library_solve(points_2d, points_3d, camera, ransac, {**bundle, "loss_scale": pixels})

    poselib.estimate_absolute_pose = with_loss
    try:
        yield
    finally:
        poselib.estimate_absolute_pose = library_solve


def partners_across_recordings(map_frames: list[Frame]) -> float:
    """The share of the map's partner pairs (refine=features_rgb's partner settings,
    the library's choice) whose two images lie in different recordings."""
    settings = TrackSettings.of(TRIANGULATION_DEFAULTS)
    poses = [frame.pose for frame in map_frames]
    chosen = tracks_module.covisible_partners(
        poses,
        [frame.camera for frame in map_frames],
        scene_depths(poses),
        settings.partners,
        settings.min_partner_angle_deg,
        settings.max_partner_angle_deg,
    )
    recordings = [recording_of(str(frame.name)) for frame in map_frames]
    pairs = [(i, j) for i, row in enumerate(chosen) for j in row]
    return sum(recordings[i] != recordings[j] for i, j in pairs) / max(len(pairs), 1)


def query_rows(structure, queries: list[Frame], settings: dict) -> dict:
    """Median errors, share within 5 cm / 5 deg and failures over the queries."""
    positions_a, angles_a = query_errors(
        structure,
        queries,
        settings["keyframes"],
        max_features=settings["max_features"],
        max_error_px=settings["max_error_px"],
        min_inliers=settings["min_inliers"],
        image_scale=settings["image_scale"],
    )
    return {
        "queries": len(queries),
        "failures": int((~np.isfinite(positions_a)).sum()),
        "median_position_m": float(np.median(positions_a)),
        "median_orientation_deg": float(np.median(angles_a)),
        "within_5cm_5deg": float(np.mean((positions_a <= WITHIN_M) & (angles_a <= WITHIN_DEG))),
        "position_errors_m": [round(p, 5) if np.isfinite(p) else None for p in positions_a],
        "orientation_errors_deg": [round(a, 4) if np.isfinite(a) else None for a in angles_a],
    }


def measured(variant: Variant, map_frames: list[Frame], query_frames: list[Frame]) -> dict:
    settings = variant.settings
    views = LazyViews(with_focal(map_frames, settings["focal"]))
    start = time.perf_counter()
    names = [str(frame.name) for frame in map_frames]
    with partners_within_recording(names, bool(settings["within_recording"])):
        structure = build_by_triangulation(
            views,
            settings["max_features"],
            quiet=True,
            image_scale=settings["image_scale"],
            **variant.triangulation,
        )
    row = {
        "variant": variant.name,
        "colour_focal": views[0].camera.fx,
        "settings": settings,
        "triangulation": variant.triangulation,
        "build_seconds": round(time.perf_counter() - start, 1),
        "share_with_point": point_share(structure),
        "against_depth": dataclasses.asdict(depth_agreement(structure, views)),
    }
    with poselib_loss_scale(settings["loss_px"]):
        row["query"] = query_rows(structure, with_focal(query_frames, settings["focal"]), settings)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--variant", action="append", required=True, help="NAME:key=value,...")
    parser.add_argument("--map-sequences", type=int, nargs="+", default=[1, 3, 5])
    parser.add_argument("--query-sequence", type=int, default=7)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    variants = [parsed_variant(text) for text in args.variant]
    if args.query_sequence in args.map_sequences:
        raise SystemExit("--query-sequence must not be one of --map-sequences")
    for sequence in [*args.map_sequences, args.query_sequence]:
        if sequence not in (1, 3, 5, 7):
            raise SystemExit(f"sequence {sequence} is not a training one: choose on 1, 3, 5, 7")

    map_frames = load_sevenscenes(ROOT, "redkitchen", "train", sequences=args.map_sequences)
    query_frames = load_sevenscenes(ROOT, "redkitchen", "train", sequences=[args.query_sequence])
    rows = []
    for variant in variants:
        row = measured(variant, map_frames, query_frames)
        summary = {k: v for k, v in row["query"].items() if not k.endswith(("_m", "_deg"))}
        summary.update(
            median_position_m=round(row["query"]["median_position_m"], 4),
            median_orientation_deg=round(row["query"]["median_orientation_deg"], 3),
            share_with_point=round(row["share_with_point"], 3),
            range_ratio=round(row["against_depth"]["median_range_ratio"], 4),
        )
        print(variant.name, summary, flush=True)
        rows.append(row)
    write_json(
        {
            "benchmark": "rgb_settings_oracle",
            "data": str(ROOT),
            "map_sequences": args.map_sequences,
            "query_sequence": args.query_sequence,
            "query_retrieval": "oracle: keyframes nearest the ground-truth pose",
            "partner_pairs_across_recordings": partners_across_recordings(map_frames),
            "machine": platform.machine(),
            "rows": rows,
        },
        args.out,
    )


if __name__ == "__main__":
    main()
