"""Run a freshly converted ncnn network once, in a process of its own.

`python relocfw/model/ncnn_probe.py PARAM BIN OUTPUTS H,W [H,W ...]` (a script: it does
not import relocfw, nor torch) loads the network as engine=ncnn does
(relocfw.model.ncnn_session) and runs one seeded image of each size through it,
extracting OUTPUTS blobs. ncnn is C++: a graph it mishandles can crash
the process (it did, before inputs were copied), which no exception handler catches;
run here first, such a crash ends this process only, and the engine reports it as a
failed conversion instead of taking the user's run down with it.
"""

from __future__ import annotations

import sys

import numpy as np


def main(arguments: list[str]) -> int:
    try:  # run as a script: its folder is on the path, relocfw's package is not imported
        from ncnn_session import NcnnSession
    except ImportError:  # imported as relocfw.model.ncnn_probe
        from relocfw.model.ncnn_session import NcnnSession

    param, weights, outputs, *sizes = arguments
    names = [f"out{number}" for number in range(int(outputs))]
    session = NcnnSession(param, weights, names, threads=1)
    generator = np.random.default_rng(0)
    for size in sizes:
        height, width = (int(side) for side in size.split(","))
        image = generator.random((1, 3, height, width), dtype=np.float32)
        answers = session.run(None, {"images": image})
        if not all(np.all(np.isfinite(answer)) for answer in answers):
            print(f"non-finite answers at {height} x {width}", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
