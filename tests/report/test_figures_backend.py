"""Importing relocfw's figure modules leaves the user's matplotlib alone: no backend
is chosen and pyplot's state machine is never used, yet figures are still written."""

import os
import subprocess
import sys
import textwrap

from relocfw.report.figures import training_curve

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def test_a_figure_is_written_as_png_and_nothing_else_is_left(tmp_path):
    history = {"loss": [3.0, 2.0, 1.5], "main": [2.0, 1.5, 1.0], "lr": [1e-3, 1e-3, 5e-4]}
    path = training_curve(history, tmp_path / "curves" / "training.png", title="t")
    assert path.read_bytes().startswith(PNG_SIGNATURE)
    assert sorted(p.name for p in path.parent.iterdir()) == ["training.png"]  # no temporary


def run_fresh(code: str) -> str:
    finished = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        timeout=300,
        env={k: v for k, v in os.environ.items() if k != "MPLBACKEND"} | {"OMP_NUM_THREADS": "1"},
    )
    assert finished.returncode == 0, finished.stderr
    return finished.stdout.strip()


def test_importing_the_figures_keeps_the_users_backend(tmp_path):
    target = str(tmp_path / "t.png")
    out = run_fresh(
        f"""
        import sys
        import matplotlib
        matplotlib.use("svg")
        import relocfw
        import relocfw.report.diagnose_figures
        from relocfw.report.figures import training_curve
        assert matplotlib.get_backend() == "svg", matplotlib.get_backend()
        path = training_curve({{"loss": [2.0, 1.0], "lr": [1e-3, 1e-3]}}, {target!r})
        assert open(path, "rb").read(8) == {PNG_SIGNATURE!r}
        assert matplotlib.get_backend() == "svg", matplotlib.get_backend()
        print("pyplot" if "matplotlib.pyplot" in sys.modules else "no pyplot")
        """
    )
    # Nothing imported pyplot, so no figure was registered in its global state either.
    assert out == "no pyplot"
