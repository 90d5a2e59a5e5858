"""bench.fine_pass: how well a start's answer must match after the coarse pass to end right."""

import json

import pytest
from conftest import SHARED_DATA

from bench import fine_pass


def test_turned_truths_of_a_large_scan_are_refined_and_judged(tmp_path, capsys):
    """The truth of an office scan's view turned 3 degrees refines back and passes the check; the record
    keeps each trial's fit after the coarse pass, at both inlier distances."""
    if not (SHARED_DATA / "real_scans.npz").is_file():
        pytest.skip(f"real scans not found in {SHARED_DATA} (shared data is not checked out here)")
    out = tmp_path / "fine.json"
    fine_pass.main(["--set", "scans:200000", "--every", "2", "--degrees", "3", "--turns", "1", "--out", str(out)])
    (trial,) = json.loads(out.read_text())["trials"]
    assert trial["pair"] == "real_scans/pcl_office1" and trial["degrees"] == 3.0
    assert trial["right"] and trial["verified"] and not trial["unpinned"]
    assert 0.0 < trial["tight"] <= trial["loose"] <= 1.0
    printed = capsys.readouterr().out
    assert "1 trials on thinned views, checked as a start's answer" in printed
    assert "right and verified: 1\n" in printed and "right and unpinned: 0\n" in printed
