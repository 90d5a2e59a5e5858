"""bench.compare: which pairs a run meets."""

import argparse

import numpy as np
import pytest

from bench import compare
from bench.harness import Pair


def test_a_run_takes_one_seed_a_range_or_a_list():
    assert compare.seeds("3") == [3]
    assert compare.seeds("0-3") == [0, 1, 2, 3]
    assert compare.seeds("0,3,5-6") == [0, 3, 5, 6]
    for bad in ("x", "5-3", "1-"):
        with pytest.raises(argparse.ArgumentTypeError):
            compare.seeds(bad)


def test_several_seeds_make_one_set_of_every_seeds_pairs_named_apart():
    def build(names, seed):
        return [Pair(name, np.zeros((3, 3)) + seed, np.zeros((3, 3)), np.eye(3), np.zeros(3), 0.05) for name in names]

    one = compare.seeded([4], build, ["a", "b"])
    assert [pair.name for pair in one] == ["a", "b"] and one[0].source[0, 0] == 4
    several = compare.seeded([0, 1], build, ["a", "b"])
    assert [pair.name for pair in several] == ["a seed 0", "b seed 0", "a seed 1", "b seed 1"]
    assert [pair.source[0, 0] for pair in several] == [0, 0, 1, 1]
