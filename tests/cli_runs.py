"""Two ways to run the `relocfw` command in a test.

`relocfw` starts a real process, as a user would: exit status, console output and the
files it leaves. Each start imports torch, Hydra, scipy and matplotlib anew (about 5 s
on 2 cores), so the end-to-end runs that do real work use it, and so does at least
one run of every refusal path.

`relocfw_here` runs the same entry point (`relocfw.app.cli.main`) in this process,
with the command line, working directory, environment and standard streams of a
process of its own, and gives back the same three things; afterwards it puts back the
environment, torch's random stream, logging and the plugin listing's cache. Refusals
that end before any work (a bad option, a broken dataset, a bad model file) cost well
under a second this way, so the many cases of one refusal path run here; runs that do
real work use `relocfw`.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path


def relocfw(args, tmp_path, cache=None, **env_extra) -> subprocess.CompletedProcess:
    """Run the CLI in a subprocess, as a user would."""
    env = {**os.environ, "RELOCFW_CACHE": str(cache or tmp_path / "cache"), **env_extra}
    return subprocess.run(
        [sys.executable, "-m", "relocfw", *args],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )


@dataclass(frozen=True)
class Finished:
    """What a run of the command leaves to look at (as subprocess.CompletedProcess)."""

    returncode: int
    stdout: str
    stderr: str


def relocfw_here(args, tmp_path, cache=None, **env_extra) -> Finished:
    """Run the CLI in this process, as `relocfw` would in its own; everything it
    changes for the run (argv, cwd, environment, streams, logging) is put back."""
    import torch

    from relocfw.app import cli
    from relocfw.app.plugin_discovery import discover_options

    env = {"RELOCFW_CACHE": str(cache or tmp_path / "cache"), **env_extra}
    saved_env = dict(os.environ)  # imports during the run may set more than `env`
    saved_rng = torch.random.get_rng_state()  # the CLI seeds torch's global stream
    saved_argv, saved_cwd = sys.argv, Path.cwd()
    root = logging.getLogger()
    saved_handlers, saved_level = list(root.handlers), root.level
    out, err = io.StringIO(), io.StringIO()
    returncode = 0
    try:
        os.environ.update(env)
        os.chdir(tmp_path)
        sys.argv = ["relocfw", *map(str, args)]
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                cli.main()
            except SystemExit as end:
                returncode = exit_status(end.code)
    finally:
        sys.argv = saved_argv
        os.chdir(saved_cwd)
        os.environ.clear()
        os.environ.update(saved_env)
        torch.random.set_rng_state(saved_rng)
        discover_options.cache_clear()  # the next run looks for plugins anew
        # Hydra points the root logger at the run's console and log file.
        for handler in root.handlers:
            if handler not in saved_handlers:
                handler.close()
        root.handlers[:] = saved_handlers
        root.setLevel(saved_level)
    return Finished(returncode, out.getvalue(), err.getvalue())


def exit_status(code: object) -> int:
    """The status a process would end with after `sys.exit(code)`."""
    if code is None:
        return 0
    if isinstance(code, int):
        return code
    print(code, file=sys.stderr)
    return 1


def users_methods(tmp_path: Path, name: str, rows: str) -> list[str]:
    """The overrides that run a user's own methods file: `rows` (YAML, one row a line)
    written as `tmp_path/mine/methods/<name>.yaml` under compare.methods, found
    through hydra.searchpath as a user's file would be."""
    folder = tmp_path / "mine" / "methods"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{name}.yaml").write_text(f"# @package compare.methods\n{rows}")
    return [f"methods={name}", f"hydra.searchpath=[file://{tmp_path / 'mine'}]"]
