"""bench.stages: where auto's time goes, step by step, beside the peers."""

import json

import pytest
from conftest import SHARED_DATA

from bench import stages


def test_the_steps_of_a_request_add_up_to_its_time(tmp_path):
    """On two clean ModelNet pairs: every step that ran is counted with its time, the steps and
    calls together take most of the request (the rest is the event loop), and the draft answers."""
    if not (SHARED_DATA / "modelnet10_test.npz").is_file():
        pytest.skip(f"ModelNet10 test shapes not found in {SHARED_DATA} (shared data is not checked out here)")
    out = tmp_path / "stages.json"
    stages.main(["--sets", "same:clean:2", "--out", str(out)])
    summary = json.loads(out.read_text())["sets"]["same:clean:2"]
    assert summary["pairs"] == 2 and summary["answers"] == {"draft": 2}
    steps = summary["steps"]
    assert {"_prepare", "_feature_guess", "_finish", "object draft call"} <= set(steps)
    assert steps["_prepare"]["pairs"] == 2 and steps["object draft call"]["total_ms"] > 0
    for row in summary["rows"]:
        spent = sum(row["steps"].values())
        assert 0.8 * row["auto"] < spent <= row["auto"]
    assert "ratio_to" not in summary  # the peers only with --peers
