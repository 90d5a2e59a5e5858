"""The torch-free geometry shared by evaluation and the service: error metrics and fitness."""

import numpy as np
import pytest

from model.geometry import (
    euler_to_matrix,
    extent,
    fitness_and_rmse,
    nearest_rotation,
    principal_axes,
    registration_errors,
    remove_duplicates,
    rotation_angle_deg,
    slides,
    summarise_errors,
)


def test_euler_errors_wrap_around_the_half_turn():
    """179 and -179 degrees about z are 2 degrees apart, not 358."""
    truth = euler_to_matrix(np.array([[179.0, 10.0, 5.0]]))
    predicted = euler_to_matrix(np.array([[-179.0, 10.0, 5.0]]))
    errors = registration_errors(predicted, np.array([[0.1, 0.0, -0.2]]), truth, np.zeros((1, 3)))
    np.testing.assert_allclose(errors["euler_abs"], [[2.0, 0.0, 0.0]], atol=1e-9)
    np.testing.assert_allclose(errors["rotation_deg"], [2.0], atol=1e-9)
    np.testing.assert_allclose(errors["trans_abs"], [[0.1, 0.0, 0.2]])
    np.testing.assert_allclose(errors["translation"], [np.hypot(0.1, 0.2)])


def test_summary_is_the_papers_table_plus_recall():
    errors = {
        "euler_abs": np.array([[1.0, 0.0, 0.0], [3.0, 0.0, 0.0]]),
        "trans_abs": np.array([[0.0, 0.0, 0.0], [0.03, 0.04, 0.0]]),
        "rotation_deg": np.array([0.5, 3.0]),
        "translation": np.array([0.005, 0.05]),
    }
    summary = summarise_errors(errors)
    assert summary["mae_r"] == pytest.approx(4.0 / 6)
    assert summary["rmse_r"] == pytest.approx(np.sqrt(10.0 / 6))
    assert summary["mae_t"] == pytest.approx(0.07 / 6)
    assert summary["rmse_t"] == pytest.approx(np.sqrt(0.0025 / 6))
    assert summary["iso_r_mean"] == pytest.approx(1.75)
    assert summary["iso_r_median"] == pytest.approx(1.75)
    assert summary["iso_t_mean"] == pytest.approx(0.0275)
    assert summary["recall_1deg_001"] == 0.5  # the first pair only
    assert summary["recall_5deg_005"] == 0.5  # 0.05 is not below 0.05


def test_fitness_counts_the_source_points_near_the_target_and_their_rms_distance():
    target = np.random.default_rng(0).uniform(-1, 1, (200, 3)) * 10  # points ~1 apart or more
    source = target[:10].copy()
    source[:7] += [0.03, 0.0, 0.04]  # 0.05 off: inliers at threshold 0.1
    source[7:] += [0.0, 0.0, 0.02]
    source[9] = [100.0, 100.0, 100.0]  # nowhere near the target
    fitness, rmse = fitness_and_rmse(source, target, threshold=0.1)
    assert fitness == pytest.approx(0.9)
    assert rmse == pytest.approx(np.sqrt((7 * 0.05**2 + 2 * 0.02**2) / 9))


def test_fitness_is_zero_when_nothing_is_within_the_threshold():
    target = np.zeros((5, 3))
    assert fitness_and_rmse(target + 1.0, target, threshold=0.5) == (0.0, 0.0)


def test_nearest_rotation_is_proper_and_removes_only_drift():
    rotation = euler_to_matrix(np.array([30.0, -20.0, 10.0]))
    drifted = rotation + np.random.default_rng(0).normal(scale=1e-4, size=(3, 3))
    np.testing.assert_allclose(nearest_rotation(drifted), rotation, atol=1e-3)
    for reflection in (np.diag([1.0, 1.0, -1.0]), -rotation):  # never answered with a reflection
        proper = nearest_rotation(reflection)
        np.testing.assert_allclose(proper @ proper.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(proper) == pytest.approx(1.0)
    assert rotation_angle_deg(nearest_rotation(rotation), rotation) < 1e-6


def test_remove_duplicates_keeps_first_occurrences_in_order():
    rng = np.random.default_rng(4)
    points = rng.normal(size=(2000, 3))
    points[::7, 2] = 0.0  # ties in one coordinate must not hide a difference in another
    copies = rng.integers(0, 2000, 500)
    shuffled = np.concatenate([points, points[copies]])[rng.permutation(2500)]
    shuffled[[10, 20]] = [[0.0, -0.0, 1.0], [-0.0, 0.0, 1.0]]  # equal as numbers: one point
    # distinct points with one sort key (x + y sqrt 3 + z sqrt 5): two points, each sent twice
    shuffled[[30, 40, 50, 60]] = [[np.sqrt(3.0), 0.0, 0.0], [0.0, 1.0, 0.0], [np.sqrt(3.0), 0.0, 0.0], [0.0, 1.0, 0.0]]
    kept = remove_duplicates(shuffled)

    _, first = np.unique(shuffled, axis=0, return_index=True)  # the reference: numpy's row-wise unique
    np.testing.assert_array_equal(kept, shuffled[np.sort(first)])
    assert len(kept) == len(np.unique(kept, axis=0))
    (zero_row,) = kept[(kept == [0.0, 0.0, 1.0]).all(axis=1)]
    assert list(np.signbit(zero_row)) == [False, True, False]  # the first of the two, as it was sent
    assert len(remove_duplicates(points)) == 2000 and remove_duplicates(points[:1]).shape == (1, 3)


def test_principal_axes_run_from_the_least_spread_to_the_most():
    rng = np.random.default_rng(0)
    turn = euler_to_matrix([30.0, -20.0, 50.0])
    cloud = (rng.normal(size=(2000, 3)) * [0.1, 1.0, 3.0]) @ turn.T + [5.0, -2.0, 1.0]
    axes = principal_axes(cloud)
    np.testing.assert_allclose(np.abs(axes.T @ turn), np.eye(3), atol=0.05)  # each axis, up to its sign


def test_slides_run_along_each_principal_axis_and_the_diagonals_between_two():
    rng = np.random.default_rng(1)
    turn = euler_to_matrix([10.0, 40.0, -70.0])
    cloud = (rng.normal(size=(2000, 3)) * [0.2, 1.0, 3.0]) @ turn.T
    start, size, axes = np.array([1.0, 2.0, 3.0]), extent(cloud), principal_axes(cloud)
    steps = (np.array(slides(start, cloud, [0.05, 0.2], [0.1])) - start) / size  # in the axes' frame below
    along, diagonal = steps[:12] @ axes, steps[12:] @ axes
    assert len(steps) == 2 * 6 + 12
    np.testing.assert_allclose(np.sort(np.abs(along).max(axis=1)), [0.05] * 6 + [0.2] * 6)
    np.testing.assert_allclose(np.sort(np.abs(along), axis=1)[:, :2], 0.0, atol=1e-12)  # one axis each
    np.testing.assert_allclose(np.linalg.norm(diagonal, axis=1), 0.1)
    np.testing.assert_allclose(
        np.sort(np.abs(diagonal), axis=1), [[0.0, 0.1 / np.sqrt(2), 0.1 / np.sqrt(2)]] * 12, atol=1e-12
    )
    assert len({tuple(np.sign(np.round(row, 9))) for row in diagonal}) == 12  # every pair of axes, every sign
    assert len(slides(start, cloud, [0.05])) == 6  # no diagonals unless asked
