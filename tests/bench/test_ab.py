"""bench.ab: variants of the pipeline's constants and settings, A/B in one process."""

import json

import numpy as np
import pytest
from conftest import SHARED_DATA

from bench import ab
from service import registration
from service.settings import Settings


def test_a_variant_names_its_constants_and_settings():
    assert ab.parse_variant("now=") == ("now", [])
    name, patches = ab.parse_variant(
        "wide=service.registration.SLIDE_GUESS_SHARE=0.02;settings.fps_max_input_points=4096"
    )
    assert name == "wide"
    assert patches == [("service.registration.SLIDE_GUESS_SHARE", 0.02), ("settings.fps_max_input_points", 4096)]
    for bad in ("=x.Y=1", "odd=SLIDE_GUESS_SHARE=1", "odd=service.registration.SLIDE_GUESS_SHARE"):
        with pytest.raises(SystemExit):
            ab.parse_variant(bad)


def test_a_variant_holds_only_while_it_runs():
    before, settings = registration.SLIDE_GUESS_SHARE, Settings()
    patches = [("service.registration.SLIDE_GUESS_SHARE", -1.0), ("settings.fps_max_input_points", 4096)]
    with ab.patched(patches, settings) as patched_settings:
        assert registration.SLIDE_GUESS_SHARE == -1.0 and patched_settings.fps_max_input_points == 4096
    assert before == registration.SLIDE_GUESS_SHARE and settings.fps_max_input_points != 4096
    for unknown in ("service.registration.NO_SUCH_CONSTANT", "settings.no_such_field"):
        with pytest.raises(SystemExit), ab.patched([(unknown, 1)], settings):
            pass


def test_a_variant_may_serve_another_repository(tmp_path):
    with ab.patched([("settings.model_repository", str(tmp_path))], Settings()) as settings:
        assert settings.model_repository == tmp_path  # a Path, as the service's model files need


def test_two_variants_meet_the_same_pairs(tmp_path):
    """On two clean ModelNet pairs (which `auto` gets right), each variant answers each pair, and the
    record says how they compare."""
    if not (SHARED_DATA / "modelnet10_test.npz").is_file():
        pytest.skip(f"ModelNet10 test shapes not found in {SHARED_DATA} (shared data is not checked out here)")
    out = tmp_path / "ab.json"
    ab.main(
        [
            "--sets",
            "same:clean:2",
            "--variant",
            "now=",
            "--variant",
            "look=service.registration.SLIDE_GUESS_SHARE=-1",
            "--out",
            str(out),
        ]
    )
    record = json.loads(out.read_text())
    summary = record["sets"]["same:clean:2"]["summary"]
    assert set(summary) == {"now", "look"} and record["sets"]["same:clean:2"]["pairs"] == 2
    for numbers in summary.values():
        assert (numbers["right"], numbers["wrong_verified"]) == (2, 0) and numbers["total_ms"] > 0
    assert summary["now"]["ratio_to_first"] == 1.0 and record["method"] == "auto"


def test_a_set_name_says_which_pairs_and_how_many():
    if not (SHARED_DATA / "modelnet10_test.npz").is_file():
        pytest.skip(f"ModelNet10 test shapes not found in {SHARED_DATA} (shared data is not checked out here)")
    from bench import harness

    counted, rotated = harness.pair_set("same:clean:3", count=7), harness.pair_set("unseen:jitter:so3", count=2)
    assert len(counted) == 3 and all(pair.name.startswith("same-clean/") for pair in counted)
    assert len(rotated) == 2 and all(pair.name.startswith("unseen-jitter-so3/") for pair in rotated)
    large = harness.pair_set("scans:200000")  # a view of every scan of the shared data over 200,000 points
    assert sorted(pair.name for pair in large) == ["real_scans/pcl_office1", "real_scans/pcl_table_scene_mug"]
    reseeded = harness.pair_set("unseen:jitter:so3", count=2, seed=1)  # the same shapes, other motions
    assert [pair.name for pair in reseeded] == [pair.name for pair in rotated]
    assert not any(np.allclose(a.rotation, b.rotation) for a, b in zip(reseeded, rotated, strict=True))
