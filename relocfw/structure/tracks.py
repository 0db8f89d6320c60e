"""An RGB-only map's 3-D points from multi-view tracks, with the map's poses held fixed.

Two-view triangulation (relocfw.structure.triangulation) gives each keypoint a
point from one partner at a time; most keypoints of a hand-held recording are seen
by many map images, and a point fixed by all of them is both more often found and
more accurate. The steps:

1. Partners chosen for geometry (relocfw.structure.covisibility).
2. Each partner pair matched (mutual nearest neighbours with Lowe's ratio test,
   relocfw.structure.matching) and the matches filtered by the epipolar geometry of
   the two known poses: a match farther than `epipolar_px` from its epipolar line in
   either image cannot be the same point.
3. Matches joined into tracks: connected components over (image, keypoint) nodes
   (union-find). A track holding two keypoints of one image is inconsistent there
   (a wrong match chained two points together): that image's keypoints leave the
   track; the rest of the track is kept.
4. Each track triangulated from ALL its views: a linear N-view DLT (in normalised
   image coordinates) then Gauss-Newton steps on the pixel reprojection error, the
   poses fixed. While a view reprojects worse than `max_reprojection_px`, the worst
   view is dropped and the track solved again. A track is kept with at least
   `min_views` views, in front of every one, all within `max_reprojection_px`, and
   two of its rays meeting at `min_angle_deg` or more.
5. Every keypoint of a kept view gets the track's one point.

All settings are scale-free (pixels, degrees, counts), so a map of any unit gets
the same tracks.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from relocfw.core.camera import PinholeCamera
from relocfw.core.errors import ConfigError
from relocfw.core.options import integer_at_least, positive_number
from relocfw.core.progress import Progress
from relocfw.core.values import Pose
from relocfw.structure.covisibility import covisible_partners, scene_depths
from relocfw.structure.features import LocalFeatures
from relocfw.structure.matching import match_against_views
from relocfw.structure.triangulation import checked_bound, world_to_camera

# Gauss-Newton steps per solve: from the DLT's start a track converges in 2-3.
GAUSS_NEWTON_STEPS = 5


@dataclass(frozen=True)
class TrackSettings:
    """How the track builder chooses partners, matches and keeps points.

    Attributes:
        partners: the most partner images per image (>= 1).
        min_partner_angle_deg: a partner's narrowest ray angle at the scene depth.
        max_partner_angle_deg: its widest (above the narrowest, below 90).
        epipolar_px: the farthest a match may lie from its epipolar line, pixels (on
            Red Kitchen correct matches lie a median 2.7 px off: the poses and the
            pinhole model are not pixel-exact there).
        max_reprojection_px: the largest reprojection error of a kept view, pixels.
        min_views: the fewest views of a kept track (>= 2).
        min_angle_deg: the widest ray angle of a kept track must reach this, degrees.
        ratio: Lowe's ratio of the pairwise matches, in (0, 1].
    """

    partners: int = 6
    min_partner_angle_deg: float = 1.5
    max_partner_angle_deg: float = 20.0
    epipolar_px: float = 4.0
    max_reprojection_px: float = 4.0
    min_views: int = 2
    min_angle_deg: float = 1.5
    ratio: float = 0.8

    @classmethod
    def of(cls, values: Mapping[str, Any], prefix: str = "triangulation") -> TrackSettings:
        """Settings from a mapping (a config block), each checked, with a ConfigError
        naming `prefix.key` for an unknown key or a value out of range."""
        if not isinstance(values, Mapping):
            raise ConfigError(f"{prefix} must be a mapping of settings, got {values!r}")
        known = {f.name for f in fields(cls)}
        for key in values:
            if key not in known:
                raise ConfigError(
                    f"{prefix}.{key} is not a track setting (known: {', '.join(sorted(known))})"
                )
        merged = {**{f.name: f.default for f in fields(cls)}, **dict(values)}
        name = f"{prefix}."
        low = positive_number(name + "min_partner_angle_deg", merged["min_partner_angle_deg"])
        high = positive_number(
            name + "max_partner_angle_deg", merged["max_partner_angle_deg"], most=90.0
        )
        if high <= low:
            raise ConfigError(
                f"{name}max_partner_angle_deg ({high:g}) must be above "
                f"{name}min_partner_angle_deg ({low:g})"
            )
        min_angle = checked_bound(name + "min_angle_deg", merged["min_angle_deg"], 0.0, 180.0)
        return cls(
            partners=integer_at_least(name + "partners", merged["partners"], 1),
            min_partner_angle_deg=low,
            max_partner_angle_deg=high,
            epipolar_px=positive_number(name + "epipolar_px", merged["epipolar_px"]),
            max_reprojection_px=positive_number(
                name + "max_reprojection_px", merged["max_reprojection_px"]
            ),
            min_views=integer_at_least(name + "min_views", merged["min_views"], 2),
            min_angle_deg=min_angle,
            ratio=positive_number(name + "ratio", merged["ratio"], most=1.0),
        )


def fundamental_matrix(
    camera_a: PinholeCamera, pose_a: Pose, camera_b: PinholeCamera, pose_b: Pose
) -> np.ndarray:
    """[3, 3] F with x_b^T F x_a = 0 for pixels (homogeneous) of one world point."""
    rotation_a, translation_a = world_to_camera(pose_a)
    rotation_b, translation_b = world_to_camera(pose_b)
    # Camera b's coordinates of a point from camera a's: X_b = R X_a + t.
    rotation = rotation_b @ rotation_a.T
    translation = translation_b - rotation @ translation_a
    cross = np.array(
        [
            [0.0, -translation[2], translation[1]],
            [translation[2], 0.0, -translation[0]],
            [-translation[1], translation[0], 0.0],
        ]
    )
    essential = cross @ rotation
    return np.linalg.inv(camera_b.matrix()).T @ essential @ np.linalg.inv(camera_a.matrix())


def epipolar_distances(
    points_a: np.ndarray,
    points_b: np.ndarray,
    camera_a: PinholeCamera,
    pose_a: Pose,
    camera_b: PinholeCamera,
    pose_b: Pose,
) -> np.ndarray:
    """[K] the larger of the two point-to-epipolar-line distances of each match, in
    pixels (each keypoint from the line its partner casts into its image)."""
    fundamental = fundamental_matrix(camera_a, pose_a, camera_b, pose_b)
    a = np.column_stack([np.asarray(points_a, np.float64), np.ones(len(points_a))])
    b = np.column_stack([np.asarray(points_b, np.float64), np.ones(len(points_b))])
    lines_in_b = a @ fundamental.T  # F x_a, per row
    lines_in_a = b @ fundamental  # F^T x_b, per row
    algebraic = np.abs(np.einsum("ij,ij->i", b, lines_in_b))
    with np.errstate(divide="ignore", invalid="ignore"):
        in_b = algebraic / np.linalg.norm(lines_in_b[:, :2], axis=1)
        in_a = algebraic / np.linalg.norm(lines_in_a[:, :2], axis=1)
    return np.nan_to_num(np.maximum(in_a, in_b), nan=np.inf)


def pair_matches(
    features: Sequence[LocalFeatures],
    poses: Sequence[Pose],
    cameras: Sequence[PinholeCamera],
    partners: Sequence[Sequence[int]],
    settings: TrackSettings,
    progress: Progress | None = None,
) -> list[tuple[int, int, np.ndarray]]:
    """The epipolar-consistent matches of every partner pair, each pair once; one
    `progress` step per image (the slow part of a track build).

    Returns:
        (i, j, [K, 2] int64 (keypoint of i, keypoint of j)) per pair with i < j.
    """
    # Each unordered pair once, matched from its lower image: one matrix product per
    # image against all its partners (relocfw.structure.matching.match_against_views).
    higher: list[set[int]] = [set() for _ in features]
    for i, chosen in enumerate(partners):
        for j in chosen:
            higher[min(i, j)].add(max(i, j))
    found = []
    for i, others in enumerate(higher):
        order = sorted(others)
        if order:
            found.extend(image_pair_matches(i, order, features, poses, cameras, settings))
        if progress is not None:
            progress.advance()  # once image i's pairs are matched
    return found


def image_pair_matches(
    i: int,
    order: Sequence[int],
    features: Sequence[LocalFeatures],
    poses: Sequence[Pose],
    cameras: Sequence[PinholeCamera],
    settings: TrackSettings,
) -> list[tuple[int, int, np.ndarray]]:
    """`pair_matches` of image `i` with its higher partners `order` (ascending)."""
    found = []
    for slot, matches in match_against_views(
        features[i], [features[j] for j in order], settings.ratio
    ):
        j = order[slot]
        if len(matches) == 0:
            continue
        distance = epipolar_distances(
            features[i].keypoints[matches[:, 0]],
            features[j].keypoints[matches[:, 1]],
            cameras[i],
            poses[i],
            cameras[j],
            poses[j],
        )
        kept = matches[distance <= settings.epipolar_px]
        if len(kept):
            found.append((i, j, kept))
    return found


def tracks_of_matches(
    counts: Sequence[int], matches: Sequence[tuple[int, int, np.ndarray]]
) -> list[np.ndarray]:
    """Multi-view tracks: connected components of the match graph over keypoints.

    Args:
        counts: keypoints per image.
        matches: (i, j, [K, 2] keypoint pairs) per image pair.

    Returns:
        Per track of two or more consistent views, an [N, 2] int64 array of (image,
        keypoint) rows, image ascending. An image holding two or more of a track's
        keypoints is left out of it (which of them is the track's is unknown).
    """
    offsets = np.concatenate([[0], np.cumsum(np.asarray(counts, dtype=np.int64))])
    total = int(offsets[-1])
    if not matches or total == 0:
        return []
    sources = np.concatenate([offsets[i] + pairs[:, 0] for i, _, pairs in matches])
    targets = np.concatenate([offsets[j] + pairs[:, 1] for _, j, pairs in matches])
    graph = coo_matrix((np.ones(len(sources)), (sources, targets)), shape=(total, total))
    _, labels = connected_components(graph, directed=False)
    matched = np.zeros(total, dtype=bool)
    matched[sources] = True
    matched[targets] = True
    nodes = np.flatnonzero(matched)
    images = np.searchsorted(offsets, nodes, side="right") - 1
    keypoints = nodes - offsets[images]
    order = np.lexsort((images, labels[nodes]))
    nodes, images, keypoints = nodes[order], images[order], keypoints[order]
    track_labels = labels[nodes]
    starts = np.flatnonzero(np.r_[True, track_labels[1:] != track_labels[:-1]])
    ends = np.r_[starts[1:], len(nodes)]
    tracks = []
    for start, end in zip(starts.tolist(), ends.tolist(), strict=True):
        track_images = images[start:end]
        unique, seen = np.unique(track_images, return_counts=True)
        keep = np.isin(track_images, unique[seen == 1])
        if keep.sum() >= 2:
            tracks.append(np.column_stack([track_images[keep], keypoints[start:end][keep]]))
    return tracks


@dataclass(frozen=True)
class TrackViews:
    """The views of B tracks of N views each, as padded arrays for batched solving.

    Attributes:
        rotations: [B, N, 3, 3] world-to-camera rotations.
        translations: [B, N, 3] world-to-camera translations.
        intrinsics: [B, N, 4] fx, fy, cx, cy.
        pixels: [B, N, 2] the observed keypoints.
        centres: [B, N, 3] camera centres.
    """

    rotations: np.ndarray
    translations: np.ndarray
    intrinsics: np.ndarray
    pixels: np.ndarray
    centres: np.ndarray


def linear_points(views: TrackViews, used: np.ndarray) -> np.ndarray:
    """[B, 3] N-view DLT points from the `used` [B, N] views (normalised coordinates,
    so each view weighs alike whatever its focal length); NaN where degenerate."""
    fx, fy, cx, cy = np.moveaxis(views.intrinsics, -1, 0)
    x = (views.pixels[..., 0] - cx) / fx
    y = (views.pixels[..., 1] - cy) / fy
    projection = np.concatenate([views.rotations, views.translations[..., None]], axis=-1)
    rows_x = x[..., None] * projection[..., 2, :] - projection[..., 0, :]
    rows_y = y[..., None] * projection[..., 2, :] - projection[..., 1, :]
    weight = used[..., None].astype(np.float64)
    system = np.concatenate([rows_x * weight, rows_y * weight], axis=1)  # [B, 2N, 4]
    homogeneous = np.linalg.svd(system)[2][:, -1, :]
    w = homogeneous[:, 3]
    finite = np.abs(w) > 1e-12 * np.abs(homogeneous[:, :3]).max(axis=1).clip(min=1e-300)
    with np.errstate(divide="ignore", invalid="ignore"):
        points = homogeneous[:, :3] / np.where(finite, w, 1.0)[:, None]
    points[~finite] = np.nan
    return points


def camera_points(views: TrackViews, points: np.ndarray) -> np.ndarray:
    """[B, N, 3] the points [B, 3] in each view's camera frame."""
    return np.einsum("bnij,bj->bni", views.rotations, points) + views.translations


def reprojection_errors(views: TrackViews, points: np.ndarray) -> np.ndarray:
    """[B, N] pixel reprojection errors; inf behind a camera or for a NaN point."""
    local = camera_points(views, points)
    fx, fy, cx, cy = np.moveaxis(views.intrinsics, -1, 0)
    depth = local[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = fx * local[..., 0] / depth + cx
        v = fy * local[..., 1] / depth + cy
        error = np.hypot(u - views.pixels[..., 0], v - views.pixels[..., 1])
    return np.where((depth > 0) & np.isfinite(error), error, np.inf)


def refined_points(views: TrackViews, used: np.ndarray, points: np.ndarray) -> np.ndarray:
    """[B, 3] the points after Gauss-Newton steps on the reprojection error of the
    `used` views (poses fixed); a track whose step fails keeps its point."""
    points = points.copy()
    fx, fy, cx, cy = np.moveaxis(views.intrinsics, -1, 0)
    for _ in range(GAUSS_NEWTON_STEPS):
        local = camera_points(views, np.nan_to_num(points))
        depth = local[..., 2]
        active = used & (depth > 1e-9)
        safe = np.where(active, depth, 1.0)
        x, y = local[..., 0] / safe, local[..., 1] / safe
        residual = np.stack(
            [fx * x + cx - views.pixels[..., 0], fy * y + cy - views.pixels[..., 1]], axis=-1
        )
        # d(pixel)/d(camera point), then through the rotation to the world point.
        zeros = np.zeros_like(x)
        d_camera = np.stack(
            [
                np.stack([fx / safe, zeros, -fx * x / safe], axis=-1),
                np.stack([zeros, fy / safe, -fy * y / safe], axis=-1),
            ],
            axis=-2,
        )  # [B, N, 2, 3]
        jacobian = d_camera @ views.rotations  # [B, N, 2, 3]
        weight = active[..., None, None].astype(np.float64)
        jacobian = jacobian * weight
        residual = residual * active[..., None]
        normal = np.einsum("bnki,bnkj->bij", jacobian, jacobian)
        gradient = np.einsum("bnki,bnk->bi", jacobian, residual)
        # A tiny damping keeps a two-view track with near-parallel rays solvable.
        normal = normal + 1e-9 * np.eye(3)
        solvable = np.isfinite(points).all(axis=1) & (np.linalg.det(normal) > 0)
        step = np.zeros_like(points)
        if solvable.any():
            step[solvable] = np.linalg.solve(normal[solvable], -gradient[solvable][..., None])[
                ..., 0
            ]
        points = points + step
    return points


def widest_ray_angle(views: TrackViews, used: np.ndarray, points: np.ndarray) -> np.ndarray:
    """[B] the widest angle in degrees between two used views' rays to the point."""
    rays = points[:, None, :] - views.centres
    rays = rays / np.linalg.norm(rays, axis=-1, keepdims=True).clip(min=1e-300)
    cosine = np.einsum("bni,bmi->bnm", rays, rays)
    both = used[:, :, None] & used[:, None, :]
    cosine = np.where(both & np.isfinite(cosine), cosine, 1.0)
    return np.degrees(np.arccos(np.clip(cosine.min(axis=(1, 2)), -1.0, 1.0)))


def solve_tracks(views: TrackViews, settings: TrackSettings) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate B tracks of N views with outlier views dropped.

    Each round solves every track from its used views (DLT, Gauss-Newton) and drops
    the worst view of each track whose worst view reprojects beyond
    `max_reprojection_px`; rounds stop when no track drops a view.

    Returns:
        points: [B, 3] float64, NaN rows for rejected tracks.
        used: [B, N] bool, the views each kept point rests on (all False when
            rejected).
    """
    count, length = views.pixels.shape[:2]
    used = np.ones((count, length), dtype=bool)
    points = np.full((count, 3), np.nan)
    # Each round drops one view of a track, so length - 1 rounds reach two views.
    for _ in range(length - 1):
        points = refined_points(views, used, linear_points(views, used))
        errors = np.where(used, reprojection_errors(views, points), -1.0)
        worst = errors.argmax(axis=1)
        over = errors[np.arange(count), worst] > settings.max_reprojection_px
        over &= used.sum(axis=1) > settings.min_views
        if not over.any():
            break
        used[np.flatnonzero(over), worst[over]] = False
    errors = reprojection_errors(views, points)
    good = (
        np.isfinite(points).all(axis=1)
        & (used.sum(axis=1) >= settings.min_views)
        & np.where(used, errors <= settings.max_reprojection_px, True).all(axis=1)
        & (widest_ray_angle(views, used, points) >= settings.min_angle_deg)
    )
    points[~good] = np.nan
    used &= good[:, None]
    return points, used


def track_views(
    tracks: Sequence[np.ndarray],
    keypoints: Sequence[np.ndarray],
    poses: Sequence[Pose],
    cameras: Sequence[PinholeCamera],
) -> TrackViews:
    """The padded views of tracks that all have the same number of views."""
    world_to_cameras = [world_to_camera(p) for p in poses]
    rotations = np.stack([r for r, _ in world_to_cameras])
    translations = np.stack([t for _, t in world_to_cameras])
    intrinsics = np.array([[c.fx, c.fy, c.cx, c.cy] for c in cameras], dtype=np.float64)
    centres = np.stack([np.asarray(p.position, np.float64) for p in poses])
    images = np.stack([track[:, 0] for track in tracks])
    pixels = np.stack(
        [np.stack([keypoints[image][point] for image, point in track.tolist()]) for track in tracks]
    ).astype(np.float64)
    return TrackViews(
        rotations=rotations[images],
        translations=translations[images],
        intrinsics=intrinsics[images],
        pixels=pixels,
        centres=centres[images],
    )


def triangulate_tracks(
    tracks: Sequence[np.ndarray],
    keypoints: Sequence[np.ndarray],
    poses: Sequence[Pose],
    cameras: Sequence[PinholeCamera],
    settings: TrackSettings,
) -> list[np.ndarray]:
    """Each image's [N_i, 3] float32 keypoint points from the tracks (NaN where none).

    Tracks are solved in batches of equal length (one vectorised solve per length).
    """
    points = [np.full((len(k), 3), np.nan, dtype=np.float32) for k in keypoints]
    lengths = np.array([len(t) for t in tracks])
    for length in np.unique(lengths).tolist():
        group = [tracks[n] for n in np.flatnonzero(lengths == length)]
        solved, used = solve_tracks(track_views(group, keypoints, poses, cameras), settings)
        for track, point, kept in zip(group, solved, used, strict=True):
            for image, keypoint in track[kept].tolist():
                points[image][keypoint] = point
    return points


def build_track_points(
    features: Sequence[LocalFeatures],
    poses: Sequence[Pose],
    cameras: Sequence[PinholeCamera],
    settings: TrackSettings,
    progress: Progress | None = None,
) -> tuple[list[np.ndarray], list[list[int]]]:
    """The 3-D point of every map keypoint that a kept track holds.

    Args:
        features: the M images' keypoints and descriptors.
        poses: their camera-to-world poses (held fixed).
        cameras: their cameras.
        settings: TrackSettings.
        progress: advanced once per image while the pairs are matched.

    Returns:
        points: per image, [N_i, 3] float32, NaN rows where no track kept the
            keypoint; keypoints of one track share its one point.
        partners: per image, the partner images it was matched with.
    """
    depths = scene_depths(poses)
    partners = covisible_partners(
        poses,
        cameras,
        depths,
        settings.partners,
        settings.min_partner_angle_deg,
        settings.max_partner_angle_deg,
    )
    matches = pair_matches(features, poses, cameras, partners, settings, progress)
    tracks = tracks_of_matches([len(f) for f in features], matches)
    keypoints = [f.keypoints for f in features]
    return triangulate_tracks(tracks, keypoints, poses, cameras, settings), partners
