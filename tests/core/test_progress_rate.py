"""Progress of a stream: the rate in units per second, and lines when the total is
unknown (a video or bag that does not say how many frames it holds)."""

import io

from relocfw.core.progress import Progress


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_a_log_line_gives_the_rate_in_the_unit():
    stream = io.StringIO()
    progress = Progress(4, "localizing", stream=stream, unit="frames")
    progress.advance(4)
    progress.close()
    (line,) = stream.getvalue().splitlines()
    assert line.startswith("localizing: 4/4 (100%)") and line.endswith(" frames/s")


def test_an_unknown_total_writes_a_line_now_and_then_and_at_the_end():
    stream = io.StringIO()
    progress = Progress(None, "localizing", stream=stream, unit="frames")
    progress.LINE_EVERY_S = 0.0  # every advance is "a while" later
    progress.advance(3)
    progress.LINE_EVERY_S = 1e9
    progress.advance(2)
    progress.close()
    lines = stream.getvalue().splitlines()
    assert [line.split(",")[0] for line in lines] == [
        "localizing: 3 frames",
        "localizing: 5 frames",
    ]
    assert lines[-1].endswith(" frames/s")


def test_a_terminal_bar_counts_frames_per_second():
    stream = Terminal()
    progress = Progress(None, "localizing", stream=stream, unit="frames")
    progress.advance(3)
    progress.close()
    assert "3frames" in stream.getvalue().replace(" ", "") and "frames/s" in stream.getvalue()
