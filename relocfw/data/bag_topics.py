"""What a bag holds, topic by topic: type, message count, rate and first / last stamp
(task=topics), so the topics a dataset or a localize run needs can be read off it.

Counts come from the bag's connections. Stamps are bag times (when each message was
recorded), not header stamps: reading them decodes no message. A ROS 1 bag's index
holds every message's time, so nothing but the index is read; a ROS 2 bag's (SQLite
or MCAP) is read once, its messages' bytes left undecoded.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from relocfw.core.errors import DataError
from relocfw.data.rosbag_source import Bag, describe, is_ros1, seconds_text


@dataclass(frozen=True)
class TopicStats:
    """One topic of a bag: its type, how many messages, their first and last bag time
    (ns; None for a topic without messages)."""

    name: str
    msgtype: str
    count: int
    first_ns: int | None
    last_ns: int | None

    @property
    def rate_hz(self) -> float | None:
        """Messages per second between the first and the last; None below two messages."""
        if self.count < 2 or self.first_ns is None or self.last_ns is None:
            return None
        span = (self.last_ns - self.first_ns) / 1e9
        return (self.count - 1) / span if span > 0 else None


def time_ranges(bag: Bag) -> dict[int, tuple[int, int]]:
    """First and last bag time (ns) of each connection id that holds messages."""
    indexes = getattr(bag.reader, "indexes", None)
    if bag.ros1 and indexes is not None:  # ROS 1: every message's time, sorted
        return {cid: (rows[0].time, rows[-1].time) for cid, rows in indexes.items() if rows}
    ranges: dict[int, tuple[int, int]] = {}
    try:
        for connection, stamp, _ in bag.reader.messages():
            first, last = ranges.get(connection.id, (stamp, stamp))
            ranges[connection.id] = (min(first, stamp), max(last, stamp))
    except Exception as error:  # rosbags, sqlite3 and OS errors of a damaged bag
        raise DataError(f"{bag.path}: cannot read the bag ({describe(error)})") from None
    return ranges


def topic_stats(path: str | Path) -> list[TopicStats]:
    """Every topic of the bag at `path`, sorted by name.

    Raises:
        DataError: naming the bag when it is missing or cannot be read.
        ConfigError: without rosbags (saying how to install it).
    """
    with Bag(path) as bag:
        ranges = time_ranges(bag)
        merged: dict[str, TopicStats] = {}
        for connection in bag.reader.connections:
            found = ranges.get(connection.id)
            seen = merged.get(connection.topic)
            firsts = [t for t in (found and found[0], seen and seen.first_ns) if t is not None]
            lasts = [t for t in (found and found[1], seen and seen.last_ns) if t is not None]
            merged[connection.topic] = TopicStats(
                connection.topic,
                connection.msgtype,
                int(connection.msgcount) + (seen.count if seen else 0),
                min(firsts, default=None),
                max(lasts, default=None),
            )
    return [merged[name] for name in sorted(merged)]


def topics_table(path: str | Path, stats: Iterable[TopicStats]) -> str:
    """The bag's topics as an aligned table with one heading line (what task=topics
    prints): topic, type, count, rate (Hz), and first and last message in seconds from
    the bag's first message, as dataset.train_time and dataset.test_time count them;
    the heading gives that first message's bag time."""
    stats = list(stats)
    messages = sum(s.count for s in stats)
    version = 1 if is_ros1(Path(path).expanduser()) else 2
    start_ns = min((s.first_ns for s in stats if s.first_ns is not None), default=None)
    start = "" if start_ns is None else f", first message at bag time {seconds_text(start_ns)} s"
    heading = (
        f"{path}: ROS {version} bag, {len(stats)} topics, {messages} messages{start} "
        "(first_s, last_s: seconds from it, as dataset.train_time / test_time count)"
    )
    rows = [("topic", "type", "count", "rate_hz", "first_s", "last_s")]
    for s in stats:
        rate = "-" if s.rate_hz is None else f"{s.rate_hz:.2f}"
        first = "-" if s.first_ns is None else f"{(s.first_ns - start_ns) / 1e9:.3f}"
        last = "-" if s.last_ns is None else f"{(s.last_ns - start_ns) / 1e9:.3f}"
        rows.append((s.name, s.msgtype, str(s.count), rate, first, last))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)) for row in rows]
    return "\n".join([heading, *(line.rstrip() for line in lines)])
