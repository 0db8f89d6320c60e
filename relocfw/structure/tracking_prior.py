"""The last confident pose of each stream of queries: refine.keyframes=track's prior.

A stream is a recording whose frames reach the refiner in order (a dataset's test
sequence, a video or bag replayed by task=localize): the part of a query's name
before its last "/" ("seq-03/frame-000042" is of stream "seq-03"). Queries without a
name, or with a name without "/", form one unnamed stream.
"""

from __future__ import annotations

from relocfw.core.values import Pose


def stream_of(name: str | None) -> str | None:
    """The stream a query belongs to; None for the one unnamed stream (kept apart
    from a recording named "", which "/frame" would give)."""
    if name is None or "/" not in name:
        return None
    return name.rsplit("/", 1)[0]


class LastConfidentPoses:
    """Per stream, the pose of its last query that did not fall back.

    A query that falls back forgets its stream's pose: the frames after a lost track
    start again from retrieval rather than from a pose that no longer fits them.
    """

    def __init__(self) -> None:
        self.poses: dict[str | None, Pose] = {}

    def prior(self, name: str | None) -> Pose | None:
        """The stream's last confident pose, None when it has none."""
        return self.poses.get(stream_of(name))

    def record(self, name: str | None, pose: Pose, fell_back: bool) -> None:
        """Remember an answered pose; a fallback (or a pose that is not finite, which
        no keyframe is near) clears the stream instead."""
        stream = stream_of(name)
        if fell_back or not pose.is_finite:
            self.poses.pop(stream, None)
        else:
            self.poses[stream] = pose

    def clear(self) -> None:
        self.poses.clear()
