"""refine=sequence end to end: the sequence rows of task=compare on one model."""

import json

from tests.cli_runs import relocfw
from tests.conftest import TINY_OVERRIDES

# A short training: the test is about the rows' plumbing, not the LSTM's accuracy.
OPTIONS = (
    "crop=centre",
    "refine=sequence",
    "refine.window=3",
    "refine.steps=20",
    "refine.hidden=8",
)
SEQUENCE = ",".join(f'"{option}"' for option in OPTIONS)


def test_compare_runs_the_sequence_rows_on_posenets_model(tmp_path):
    run_dir = tmp_path / "compare"
    args = [
        *TINY_OVERRIDES,
        "task=compare",
        "compare.crop_seeds=null",
        "~compare.methods",
        '+compare.methods={PoseNet:["crop=centre"],'
        f'Causal:[{SEQUENCE}],Bidirectional:[{SEQUENCE},"refine.direction=bidirectional"]}}',
    ]
    result = relocfw([*args, f"hydra.run.dir={run_dir}"], tmp_path)
    assert result.returncode == 0, result.stderr
    # The LSTM reads the trained network's descriptors: one network for every row.
    assert result.stdout.count("(trained)") == 1
    summary = json.loads((run_dir / "summary_synthetic.json").read_text())
    rows = {row["method"]: row for row in summary}
    assert set(rows) == {"PoseNet", "Causal", "Bidirectional", "mean training pose"}
    centre = rows["PoseNet"]["median_position_m"]
    for name, row in rows.items():
        if name in ("Causal", "Bidirectional"):  # its own answer, from the frames of the recording
            assert row["median_position_m"] != centre, name
