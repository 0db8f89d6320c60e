"""How far a genuine int8 graph's answers lie from torch's, against a graph of other
weights: the evidence for `relocfw.model.onnx_engine.INT8_TOLERANCE`.

Two models are trained through the CLI with the tests' tiny settings
(tests/conftest.py TINY_OVERRIDES: 32-pixel input, 1/8 width, three training steps,
the model the CLI tests quantise), seeds 0 and 1. Model 0's full graph is quantised
(`--int8`, static by default, calibrated on its map images as task=relocalize does),
then opened --opens times: each open draws fresh check images, as the engine's own
check does (`int8_deviations`). Reported per output: the largest deviation of the
genuine graph from model 0's torch answers, and the smallest deviation of the same
graph from model 1's torch answers (a graph of other weights, which the bound exists to
refuse). A bound between the two columns refuses the second and never the first.

    .venv/bin/python benchmarks/int8_deviation.py --out benchmarks/results/int8_deviation.json
"""

from __future__ import annotations

import argparse
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np
from common import write_json  # benchmarks/, the script's own folder

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from relocfw.core.imaging import read_rgb  # noqa: E402
from relocfw.model.cpu_flags import int8_saturation_reason  # noqa: E402
from relocfw.model.model_file import load_model  # noqa: E402
from relocfw.model.onnx_engine import (  # noqa: E402
    INT8_TOLERANCE,
    INT8_UNITS,
    EngineOptions,
    int8_deviations,
    onnx_engine,
)
from relocfw.model.onnx_graphs import FULL  # noqa: E402
from tests.cli_runs import relocfw  # noqa: E402  (the CLI in a subprocess, as the tests run it)
from tests.conftest import TINY_OVERRIDES  # noqa: E402


def train(home: Path, seed: int) -> tuple[Path, Path]:
    """The tests' tiny model of one seed: its file and its map images' folder."""
    home.mkdir()
    result = relocfw([*TINY_OVERRIDES, f"seed={seed}", f"hydra.run.dir={home / 'run'}"], home)
    if result.returncode != 0:
        raise SystemExit(f"training seed {seed} failed:\n{result.stderr}")
    scene = next((home / "cache" / "scenes").iterdir())
    return home / "run" / "model.relocfw", scene / "seq-03"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--opens", type=int, default=40, help="check-image draws per graph")
    parser.add_argument("--int8", default="static", choices=["static", "static_8bit"])
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()

    import onnxruntime

    with tempfile.TemporaryDirectory(prefix="relocfw-int8-deviation-") as folder:
        (own, images), (other, _) = (train(Path(folder) / f"seed{s}", s) for s in (0, 1))
        network = load_model(own, "cpu").backbone
        calibration = [read_rgb(path) for path in sorted(images.glob("*.color.png"))]
        options = EngineOptions(threads=1, int8=args.int8, scout=True)
        onnx_engine(network, own, options, calibration)  # writes the int8 full graph
        graph = next(own.parent.glob(f"{own.name}-full.int8-*.onnx"))
        session = onnxruntime.InferenceSession(str(graph), providers=["CPUExecutionProvider"])
        others = load_model(other, "cpu").backbone
        genuine = [int8_deviations(session, network, FULL) for _ in range(args.opens)]
        foreign = [int8_deviations(session, others, FULL) for _ in range(args.opens)]

    rows = {
        name: {
            "unit": INT8_UNITS[name],
            "bound": INT8_TOLERANCE[name],
            "genuine_largest": max(d[name] for d in genuine),
            "genuine_median": float(np.median([d[name] for d in genuine])),
            "other_weights_smallest": min(d[name] for d in foreign),
        }
        for name in genuine[0]
    }
    report = {
        "int8": args.int8,
        "opens": args.opens,
        "machine": platform.processor() or platform.machine(),
        "int8_saturation_reason": int8_saturation_reason(),
        "onnxruntime": onnxruntime.__version__,
        "outputs": rows,
    }
    write_json(report, args.out)
    print(f"{'output':<12} {'genuine max':>12} {'median':>8} {'other min':>10} {'bound':>6}")
    for name, row in rows.items():
        print(
            f"{name:<12} {row['genuine_largest']:>12.3g} {row['genuine_median']:>8.3g} "
            f"{row['other_weights_smallest']:>10.3g} {row['bound']:>6g}  {row['unit']}"
        )


if __name__ == "__main__":
    main()
