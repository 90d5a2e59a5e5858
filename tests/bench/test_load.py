"""bench.load: what its records say about memory."""

import numpy as np
import pytest

from bench import load


def test_memory_is_summed_up_as_first_end_max_and_the_trend_from_a_time_on():
    samples = np.array([(0.0, 100.0), (30.0, 140.0), (60.0, 130.0), (90.0, 150.0)])
    whole = load.rss_summary(samples)
    assert (whole["first"], whole["end"], whole["max"]) == (100.0, 150.0, 150.0)
    assert whole["slope_per_min"] == pytest.approx(np.polyfit(samples[:, 0], samples[:, 1], 1)[0] * 60)
    assert load.rss_summary(samples, slope_from_s=60.0)["slope_per_min"] == pytest.approx(40.0)
