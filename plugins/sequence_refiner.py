"""refine=sequence: a VidLoc-style recurrent model over the frames before each query.

The query contract. A query is a frame of a recording; its name says which (the folder
part of the frame name: "seq-03/frame-000042" is frame 42 of recording "seq-03"), and
the queries of one recording arrive in recording order, as every relocfw dataset lists
them. The pose of a query is the last output of the recurrent network run over the
descriptors of the `window` most recent frames of its recording, itself included: a
query never reads a frame after it, in either direction mode, so the answer is one a
robot can compute when the frame arrives. At the start of a recording fewer frames
exist and the window is shorter (trained for, see `SequenceRefiner.train`). A
query whose name was seen before (the untimed warm-up query, or a second pass over a
split) starts its recording's history afresh, so the same split gives the same answers.

Fitting: the map images' descriptors, grouped by recording in the order given, are cut
into clips and the network (relocfw.model.sequence_network) is trained on them with
Adam, seeded; positions are regressed in the map positions' normalised frame as the
backbones do. The backbone is frozen; VidLoc trains CNN and LSTM end to end.

The answer never uses the network's pose of the query (it uses the descriptor), so
Monte Carlo or crop sampling is refused as for refine=retrieval.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import ClassVar

import numpy as np
import torch

from relocfw.core.errors import ConfigError, DataError
from relocfw.core.options import integer_at_least, probability
from relocfw.core.progress import Progress
from relocfw.core.refinement import MapImage, PoseRefiner, Refined, RefineQuery
from relocfw.core.standardise import ZScore, check_features
from relocfw.core.values import Pose
from relocfw.model.sequence_network import SequencePoseNetwork, checked_direction
from relocfw.model.state_checks import state_mismatch


def recording_of(name: str) -> str:
    """The recording a frame belongs to: its name's folder part ("" for a bare name)."""
    return name.rsplit("/", 1)[0] if "/" in name else ""


def recordings_of(names: Sequence[str]) -> list[np.ndarray]:
    """Row indices of each recording, in the order the names give (recording order)."""
    rows: dict[str, list[int]] = {}
    for row, name in enumerate(names):
        rows.setdefault(recording_of(name), []).append(row)
    return [np.asarray(r) for r in rows.values()]


class SequenceRefiner(PoseRefiner):
    """The pose of each query from its recording's last `window` frames (see module).

    Args:
        window: frames the network sees per query, the query included (>= 1).
        direction: "causal" (forward LSTM) or "bidirectional" (VidLoc's).
        hidden: LSTM state size per direction.
        steps, batch_size, lr: training of the recurrent network (Adam).
        beta: weight of the quaternion error against the normalised position error.
        input_dropout: dropout on the descriptors in training.
        seed: the network's initial weights and its clips.
    """

    replaces_network_pose: ClassVar[bool] = True

    def __init__(
        self,
        window: int = 20,
        direction: str = "causal",
        hidden: int = 256,
        steps: int = 1500,
        batch_size: int = 32,
        lr: float = 1e-3,
        beta: float = 1.0,
        input_dropout: float = 0.2,
        seed: int = 0,
    ) -> None:
        self.window = integer_at_least("refine.window", window, 1)
        self.hidden = integer_at_least("refine.hidden", hidden, 1)
        self.steps = integer_at_least("refine.steps", steps, 1)
        self.batch_size = integer_at_least("refine.batch_size", batch_size, 1)
        self.lr = float(lr)
        if not self.lr > 0:
            raise ConfigError(f"refine.lr must be > 0, got {lr}")
        self.beta = float(beta)
        if not self.beta >= 0:
            raise ConfigError(f"refine.beta must be >= 0, got {beta}")
        if not 0 <= probability("refine.input_dropout", input_dropout) < 1:
            raise ConfigError(f"refine.input_dropout must be in [0, 1), got {input_dropout}")
        self.input_dropout = float(input_dropout)
        self.seed = integer_at_least("refine.seed", seed, 0)
        self.direction = checked_direction(direction)  # now, not after training
        self.network: SequencePoseNetwork | None = None
        self.history: dict[str, list[np.ndarray]] = {}
        self.seen: dict[str, set[str]] = {}

    def fit(self, views: Sequence[MapImage], descriptors: np.ndarray, quiet: bool = True) -> None:
        features = check_features(descriptors)
        if len(views) != len(features):
            raise DataError(f"fit: {len(views)} map images but {len(features)} descriptors")
        if all(view.name.startswith("map image ") for view in views):
            raise DataError(
                "refine=sequence needs the map images' frame names to know their recordings: "
                "Relocalizer.fit(images, poses, frames=...) with the dataset's frames"
            )
        self.zscore = ZScore().fit(features)
        positions = np.stack([v.pose.position for v in views])
        quaternions = np.stack([v.pose.quaternion for v in views])
        self.position_mean = positions.mean(axis=0)
        # One scale for all axes (the backbones' normalised frame): the RMS distance
        # of the map's cameras from their mean; 1 for a map at one point.
        spread = float(np.sqrt(((positions - self.position_mean) ** 2).sum(axis=1).mean()))
        self.position_scale = spread if spread > 0 else 1.0
        clips = ClipSampler(
            self.zscore(features).astype(np.float32),
            ((positions - self.position_mean) / self.position_scale).astype(np.float32),
            quaternions.astype(np.float32),
            recordings_of([v.name for v in views]),
        )
        self.network = self.train(clips, features.shape[1], quiet)
        self.history, self.seen = {}, {}

    def train(self, clips: ClipSampler, feature_dim: int, quiet: bool) -> SequencePoseNetwork:
        rng = np.random.default_rng(self.seed)
        with torch.random.fork_rng(devices=[]):  # the caller's stream is left as it was
            torch.manual_seed(self.seed)
            network = SequencePoseNetwork(
                feature_dim, self.hidden, self.direction, self.input_dropout
            )
            optimiser = torch.optim.Adam(network.parameters(), lr=self.lr)
            schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, self.steps)
            progress = Progress(self.steps, "training the sequence model", quiet=quiet)
            network.train()
            # Train the outputs a query uses. A causal output at step t is a query with
            # t + 1 frames of history, so full windows train every history length; a
            # bidirectional output at t < last has seen later frames, which no query
            # does, so only the last output of clips of every length is trained.
            causal = self.direction == "causal"
            for _ in range(self.steps):
                length = self.window if causal else int(rng.integers(1, self.window + 1))
                descriptors, positions, quaternions = clips.batch(rng, self.batch_size, length)
                predicted, rotation = network(descriptors)
                if not causal:
                    predicted, rotation = predicted[:, -1:], rotation[:, -1:]
                    positions, quaternions = positions[:, -1:], quaternions[:, -1:]
                loss = pose_loss(predicted, rotation, positions, quaternions, self.beta)
                optimiser.zero_grad()
                loss.backward()
                optimiser.step()
                schedule.step()
                progress.advance()
            progress.close()
        return network.eval()

    def reset(self) -> None:
        """Forget every recording's history: a new pass over the queries begins."""
        self.history, self.seen = {}, {}

    def refine(self, query: RefineQuery) -> Refined:
        if self.network is None:
            raise ConfigError("the refiner is not fitted: fit the Relocalizer's map first")
        if not query.name:
            raise ConfigError(
                "refine=sequence needs each query's frame name (its recording and place "
                "in it): localize through Relocalizer.localize(image, name=...) / "
                "localize_many(..., names=...)"
            )
        started = time.perf_counter()
        descriptor = check_features(np.asarray(query.descriptor)[None], len(self.zscore.mean))
        recording = recording_of(query.name)
        frames, seen = (
            self.history.setdefault(recording, []),
            self.seen.setdefault(recording, set()),
        )
        if query.name in seen:  # a second pass (or the warm-up query): start afresh
            frames.clear()
            seen.clear()
        seen.add(query.name)
        frames.append(self.zscore(descriptor)[0].astype(np.float32))
        del frames[: -self.window]  # only the window is ever read
        with torch.inference_mode():
            position, quaternion = self.network(torch.from_numpy(np.stack(frames))[None])
        position = position[0, -1].double().numpy() * self.position_scale + self.position_mean
        pose = Pose(position, quaternion[0, -1].double().numpy())
        return Refined(pose, seconds={"sequence": time.perf_counter() - started})

    def state(self) -> dict[str, torch.Tensor]:
        """The standardisation, the position frame and the network's weights; the
        options (window, direction, hidden) are the constructor's, which model files
        keep. The recordings' histories are not state: a loaded model starts afresh."""
        if self.network is None:
            raise ConfigError("the refiner is not fitted: fit the Relocalizer's map first")
        weights = {f"network.{k}": v.detach().clone() for k, v in self.network.state_dict().items()}
        return {
            **self.zscore.state(),
            "position_mean": torch.from_numpy(self.position_mean.astype(np.float64)),
            "position_scale": torch.tensor(self.position_scale, dtype=torch.float64),
            **weights,
        }

    def load_state(self, state: dict[str, torch.Tensor]) -> None:
        """What `state` returned. A model file is data from anyone: a state that does
        not fit these options is a DataError naming the key, before anything is kept."""
        for key in ("mean", "std", "position_mean", "position_scale"):
            if not isinstance(state.get(key), torch.Tensor):
                raise DataError(f"sequence state: {key} is missing or not a tensor")
        mean = state["mean"]
        if mean.ndim != 1 or state["std"].shape != mean.shape:
            raise DataError("sequence state: mean and std must be vectors of one length")
        position_mean = state["position_mean"].double().numpy()
        scale = state["position_scale"]
        if position_mean.shape != (3,) or scale.numel() != 1:
            raise DataError("sequence state: position_mean must be [3], position_scale one value")
        scale = float(scale.item())
        if not (np.isfinite(position_mean).all() and np.isfinite(scale) and scale > 0):
            raise DataError("sequence state: position_mean or position_scale is NaN, inf or <= 0")
        for key in ("mean", "std"):
            if not torch.isfinite(state[key]).all():
                raise DataError(f"sequence state: {key} holds NaN or infinite values")
        if not (state["std"] > 0).all():
            raise DataError("sequence state: std must be > 0")
        weights = {k[len("network.") :]: v for k, v in state.items() if k.startswith("network.")}
        self.check_weight_shapes(len(mean), weights)
        with torch.random.fork_rng(devices=[]):  # building it draws initial weights
            network = SequencePoseNetwork(
                len(mean), self.hidden, self.direction, self.input_dropout
            )
        try:
            network.load_state_dict(weights, strict=True)
        except RuntimeError as error:
            first = str(error).strip().splitlines()[0]
            raise DataError(
                f"sequence state: the network's weights do not fit refine.hidden={self.hidden}, "
                f"refine.direction={self.direction} and {len(mean)}-d descriptors ({first})"
            ) from error
        if not all(torch.isfinite(w).all() for w in weights.values()):
            raise DataError("sequence state: the network's weights hold NaN or infinite values")
        self.zscore = ZScore().load_state(state)
        self.position_mean, self.position_scale = position_mean, scale
        self.network = network.eval()
        self.history, self.seen = {}, {}

    def check_weight_shapes(self, feature_dim: int, weights: dict[str, torch.Tensor]) -> None:
        """A DataError when `weights` do not fit these options, found without building
        the network (a crafted refine.hidden=10**9 would allocate terabytes)."""
        options = (feature_dim, self.hidden, self.direction, self.input_dropout)
        try:
            mismatch = state_mismatch(lambda: SequencePoseNetwork(*options), weights)
        except RuntimeError as error:  # sizes past what a tensor can hold
            mismatch = str(error).strip().splitlines()[0]
        if mismatch is not None:
            raise DataError(
                f"sequence state: the network's weights do not fit refine.hidden={self.hidden}, "
                f"refine.direction={self.direction} and {feature_dim}-d descriptors ({mismatch})"
            )


def pose_loss(
    positions: torch.Tensor,
    quaternions: torch.Tensor,
    true_positions: torch.Tensor,
    true_quaternions: torch.Tensor,
    beta: float,
) -> torch.Tensor:
    """Mean position distance + beta x quaternion distance, the quaternion's sign free
    (q and -q are one rotation)."""
    position_error = (positions - true_positions).norm(dim=-1)
    same = (quaternions - true_quaternions).norm(dim=-1)
    flipped = (quaternions + true_quaternions).norm(dim=-1)
    return (position_error + beta * torch.minimum(same, flipped)).mean()


class ClipSampler:
    """Random clips of consecutive map frames, of one length per batch."""

    def __init__(
        self,
        descriptors: np.ndarray,
        positions: np.ndarray,
        quaternions: np.ndarray,
        recordings: list[np.ndarray],
    ) -> None:
        self.descriptors = descriptors
        self.positions = positions
        self.quaternions = quaternions
        self.recordings = recordings
        sizes = np.array([len(r) for r in recordings], dtype=np.float64)
        self.weights = sizes / sizes.sum()

    def batch(
        self, rng: np.random.Generator, size: int, length: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        rows = []
        for recording in rng.choice(len(self.recordings), size=size, p=self.weights):
            frames = self.recordings[recording]
            span = min(length, len(frames))
            start = int(rng.integers(0, len(frames) - span + 1))
            clip = frames[start : start + span]
            # A recording shorter than the clip: its first frame repeated in front,
            # as a camera that stood still.
            rows.append(np.concatenate([np.full(length - span, clip[0]), clip]))
        rows = np.stack(rows)
        return (
            torch.from_numpy(self.descriptors[rows]),
            torch.from_numpy(self.positions[rows]),
            torch.from_numpy(self.quaternions[rows]),
        )
