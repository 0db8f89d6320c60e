"""Losses of scene-coordinate regression, with and without depth.

With depth (SCoRF, DSAC* with depth): each cell's target is a measured world point;
the loss is the distance to it, linear near the target and growing as a square root
past DEPTH_SOFT_CLAMP_M, so a few wrong depth readings (object edges, mixed pixels)
pull less than the many right ones. Not squared: a squared loss is the mean, which
one bad reading moves; a tanh clamp would stop the gradient of cells still metres
off at the start, when the head predicts the scene's centre everywhere.

Without depth (ACE, DSAC* RGB-only): each cell's target is only its pixel. A predicted
point is "valid" when it lies in front of the map camera between MIN_DEPTH and
MAX_DEPTH and reprojects within MAX_REPROJECTION_PX of the cell's pixel; a valid
point's loss is its reprojection error e, softly clamped as tau * tanh(e / tau), and
tau shrinks over training from `tau_start` to `tau_end` (a curriculum: early on every
cell pulls, later only those already near their pixel refine while the rest, likely
ambiguous, stop dragging the head). An invalid point is pulled towards the point on
its pixel's ray at `prior_depth`: a reprojection loss has no gradient towards the
front of the camera from behind it, so those points need another target first.
"""

from __future__ import annotations

import math

import torch

DEPTH_SOFT_CLAMP_M = 1.0  # past this distance the depth loss grows as a square root
MIN_DEPTH = 0.1  # nearer than this (map units) a point is invalid: it would be in the lens
MAX_DEPTH = 1000.0  # farther: invalid (a point at infinity reprojects well from anywhere)
MAX_REPROJECTION_PX = 1000.0  # farther from its pixel: invalid, pulled to its ray instead


def depth_loss(predicted: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """The mean robust distance of [N, 3] predicted world points to their [N, 3] targets."""
    distance = (predicted - targets).norm(dim=1)
    clamp = DEPTH_SOFT_CLAMP_M
    # d up to the clamp, then 2 sqrt(clamp d) - clamp: the same value and slope (1)
    # at d = clamp, so the two pieces join without a kink.
    far = 2.0 * torch.sqrt(clamp * distance.clamp(min=clamp)) - clamp
    return torch.where(distance <= clamp, distance, far).mean()


def curriculum_threshold(step: int, steps: int, tau_start: float, tau_end: float) -> float:
    """The reprojection clamp at `step` of `steps`: tau_start to tau_end on a half cosine."""
    progress = min(max(step / max(steps - 1, 1), 0.0), 1.0)
    return tau_end + (tau_start - tau_end) * 0.5 * (1.0 + math.cos(math.pi * progress))


def reprojection_loss(
    predicted: torch.Tensor,
    pixels: torch.Tensor,
    intrinsics: torch.Tensor,
    rotations: torch.Tensor,
    translations: torch.Tensor,
    tau: float,
    prior_depth: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The RGB-only loss of a batch and each cell's reprojection error.

    Args:
        predicted: [N, 3] world points.
        pixels: [N, 2] each cell's pixel (x, y) in its map image.
        intrinsics: [N, 4] (fx, fy, cx, cy) of each cell's map image.
        rotations: [N, 3, 3] world-to-camera rotations.
        translations: [N, 3] world-to-camera translations.
        tau: the soft clamp of valid points' errors, pixels.
        prior_depth: the depth along its ray an invalid point is pulled to.

    Returns:
        The mean loss over the N cells, and [N] reprojection errors in pixels (inf
        where the point is not in front of the camera), detached.
    """
    in_camera = torch.einsum("nij,nj->ni", rotations, predicted) + translations
    z = in_camera[:, 2]
    fx, fy, cx, cy = intrinsics.unbind(dim=1)
    safe_z = z.clamp(min=MIN_DEPTH)
    projected = torch.stack(
        [fx * in_camera[:, 0] / safe_z + cx, fy * in_camera[:, 1] / safe_z + cy], dim=1
    )
    error = (projected - pixels).norm(dim=1)
    valid = (z > MIN_DEPTH) & (z < MAX_DEPTH) & (error < MAX_REPROJECTION_PX)
    clamped = tau * torch.tanh(error / tau)
    # The point on the pixel's ray at prior_depth, in camera coordinates.
    ray_point = torch.stack(
        [(pixels[:, 0] - cx) / fx, (pixels[:, 1] - cy) / fy, torch.ones_like(z)], dim=1
    )
    pull = (in_camera - ray_point * prior_depth).norm(dim=1)
    loss = torch.where(valid, clamped, pull)
    shown = torch.where(z > 0, error, torch.full_like(error, math.inf))
    return loss.mean(), shown.detach()
