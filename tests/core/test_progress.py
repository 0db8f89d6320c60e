"""Progress: nothing when quiet, plain lines in logs, a tqdm bar on a terminal."""

import io

from relocfw.core.progress import Progress


class Terminal(io.StringIO):
    def isatty(self):
        return True


def run(progress, steps=10):
    for _ in range(steps):
        progress.advance(suffix="loss 0.5")
    progress.close()


def test_quiet_writes_nothing():
    for stream in (io.StringIO(), Terminal()):
        run(Progress(10, "work", quiet=True, stream=stream))
        assert stream.getvalue() == ""


def test_a_log_gets_one_plain_line_per_quarter():
    stream = io.StringIO()
    run(Progress(10, "relocalizing", stream=stream))
    lines = stream.getvalue().splitlines()
    assert len(lines) == 4 and "\r" not in stream.getvalue()
    assert lines[-1].startswith("relocalizing: 10/10 (100%)") and lines[-1].endswith("loss 0.5")


def test_a_jump_past_several_quarters_writes_one_line():
    stream = io.StringIO()
    progress = Progress(8, "fit", stream=stream)
    progress.advance(8)
    progress.close()
    assert len(stream.getvalue().splitlines()) == 1


def test_a_terminal_gets_a_tqdm_bar():
    stream = Terminal()
    run(Progress(10, "training", stream=stream))
    text = stream.getvalue()
    assert "training" in text and "10/10" in text and "\r" in text  # redrawn in place
    assert "loss 0.5" in text
