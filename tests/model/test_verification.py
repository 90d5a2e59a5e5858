"""The answer check and the spacing-based refinement in model.geometry, on synthetic clouds."""

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from model.geometry import (
    MAX_DRIFT_SPACINGS,
    MIN_CONSTRAINT,
    AlignmentClouds,
    AlignmentScore,
    apply_transform,
    inlier_constraint,
    judge,
    missed,
    point_spacing,
    refine,
    rotation_angle_deg,
    verify_alignment,
)


def grid(step: float, size: int = 20) -> np.ndarray:
    axis = np.arange(size) * step
    return np.stack(np.meshgrid(axis, axis, [0.0]), axis=-1).reshape(-1, 3)


def blob(rng: np.random.Generator, count: int = 1500) -> np.ndarray:
    """A closed bumpy surface, stretched per axis (no symmetry a check could be fooled by)."""
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    bumps = 1.0 + 0.2 * np.sin(3.0 * directions[:, 0] + 2.0 * directions[:, 1]) * np.cos(2.0 * directions[:, 2])
    return directions * bumps[:, None] * np.array([1.0, 0.7, 0.5])


def pair(seed: int = 0, jitter: float = 0.0):
    """Two independent samplings of one surface (no shared point), the second moved."""
    rng = np.random.default_rng(seed)
    surface = blob(rng, 3000)
    source, target = surface[:1500], surface[1500:]
    rotation = Rotation.from_euler("zyx", [30, 20, 10], degrees=True).as_matrix()
    translation = np.array([0.3, -0.2, 0.1])
    target = apply_transform(target, rotation, translation) + rng.normal(0, jitter, target.shape)
    return source, target, rotation, translation


def turned(rotation, translation, degrees: float, centre: np.ndarray):
    """The transform followed by a turn of `degrees` about the x axis through `centre`."""
    turn = Rotation.from_euler("x", degrees, degrees=True).as_matrix()
    return turn @ rotation, turn @ translation + centre - turn @ centre


def test_spacing_is_the_grid_step_and_ignores_duplicates():
    points = grid(0.05)
    assert point_spacing(points) == pytest.approx(0.05)
    assert point_spacing(np.concatenate([points, points[:50]])) == pytest.approx(0.05)
    assert point_spacing(points, max_queries=100) == pytest.approx(0.05)


def test_spacing_is_the_median_nearest_neighbour_distance_on_any_threads():
    rng = np.random.default_rng(3)
    points = blob(rng, 6000) * 10.0 + 1e3  # away from the origin, as map coordinates are
    points = np.concatenate([points, points[:200]])  # duplicates are no neighbours
    queries = points[np.random.default_rng(0).choice(len(points), size=4096, replace=False)]
    nearest = cKDTree(points).query(queries, k=2)[0][:, 1]
    expected = np.median(nearest[nearest > 0])
    assert point_spacing(points) == pytest.approx(expected, rel=1e-12)
    assert point_spacing(points, threads=2) == point_spacing(points)


def test_score_uses_the_spacing_not_the_extent():
    """A shift of 5 grid steps keeps no inlier, whatever the cloud's size."""
    points = grid(0.05)
    exact = AlignmentClouds(points, points).score(np.eye(3), np.zeros(3))
    assert (exact.fitness, exact.overlap, exact.inlier_rmse) == (1.0, 1.0, 0.0)
    assert exact.threshold == pytest.approx(1.5 * 0.05)
    shifted = AlignmentClouds(points, points).score(np.eye(3), np.array([0.0, 0.0, 0.25]))
    assert shifted.fitness == 0.0 and shifted.inliers == 0


def test_overlap_counts_the_other_way():
    points = grid(0.05)
    half = points[points[:, 0] < 0.45]  # 9 of the 20 columns
    score = AlignmentClouds(half, points).score(np.eye(3), np.zeros(3))
    assert score.fitness == 1.0
    # The 10th column lies one step (< 1.5 steps) from the half's last one, so it counts as covered.
    assert score.overlap == pytest.approx(10 / 20)


def test_surface_fitness_leaves_out_the_sources_isolated_points():
    """Points with no other source point within ISOLATED_SPACINGS spacings (outliers) count in the
    fitness, not in the surface fitness; a shift that lays half the surface on the target halves it."""
    points = grid(0.05)
    outliers = np.array([[0.5, 0.5, 1.0], [0.2, 0.7, -1.0], [5.0, 5.0, 5.0], [0.5, 0.5, 0.4]])  # 6-8+ spacings off
    clouds = AlignmentClouds(np.concatenate([points, outliers]), points)
    assert clouds.score(np.eye(3), np.zeros(3)).fitness == pytest.approx(400 / 404)
    assert clouds.surface_fitness(np.eye(3), np.zeros(3)) == 1.0
    assert clouds.surface_fitness(np.eye(3), np.array([0.5, 0.0, 0.0])) == pytest.approx(11 / 20)
    lone = AlignmentClouds(outliers, points, spacing=0.05)  # no surface: the fitness itself
    assert lone.surface_fitness(np.eye(3), np.zeros(3)) == lone.score(np.eye(3), np.zeros(3)).fitness == 0.0


def test_constraint_is_zero_on_a_plane_and_positive_on_a_closed_surface():
    plane = grid(0.05)
    assert inlier_constraint(plane, np.tile([0.0, 0.0, 1.0], (len(plane), 1))) == pytest.approx(0.0, abs=1e-12)
    sphere = blob(np.random.default_rng(1)) / np.array([1.0, 0.7, 0.5])  # the unit sphere, normals = points
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    # A sphere turns about its centre without leaving its surface: rotations are free, shifts are not.
    assert inlier_constraint(sphere, sphere) == pytest.approx(0.0, abs=1e-9)
    source, target, rotation, translation = pair()
    assert AlignmentClouds(source, target).score(rotation, translation).constraint > MIN_CONSTRAINT


@pytest.mark.parametrize("jitter", [0.0, 0.01])
def test_right_answer_is_verified_and_wrong_ones_are_not(jitter):
    source, target, rotation, translation = pair(jitter=jitter)
    right = verify_alignment(source, target, rotation, translation)
    assert right.verified, right.reason
    centre = apply_transform(source, rotation, translation).mean(axis=0)
    for degrees in (4.0, 15.0, 60.0):
        wrong = verify_alignment(source, target, *turned(rotation, translation, degrees, centre))
        assert not wrong.verified, degrees
        assert wrong.reason
    shift = verify_alignment(source, target, rotation, translation + np.array([0.0, 0.0, 0.15]))
    assert not shift.verified and shift.reason


def test_judge_names_each_failure():
    good = AlignmentScore(0.05, 0.075, 0.9, 0.03, 0.9, 500, 0.1)
    assert judge(good, 0.0) == (True, None)
    assert "match" in judge(good._replace(inliers=5), 0.0).reason
    assert "overlap" in judge(good._replace(overlap=0.05), 0.0).reason
    assert "pin" in judge(good._replace(constraint=0.001), 0.0).reason
    assert "settled" in judge(good, 2 * MAX_DRIFT_SPACINGS).reason
    assert not judge(good, float("nan")).verified


def test_an_answer_failing_on_the_constraint_alone_is_unpinned():
    """A plane laid on itself fits and has settled, but nothing stops it sliding: unpinned. An
    answer that fails on anything else, or passes, is not."""
    plane = grid(0.05)
    on_itself = verify_alignment(plane, plane, np.eye(3), np.zeros(3))
    assert not on_itself.verified and "pin" in on_itself.reason and on_itself.unpinned
    lifted = verify_alignment(plane, plane, np.eye(3), np.array([0.0, 0.0, 0.5]))  # no point matches
    assert not lifted.verified and not lifted.unpinned
    source, target, rotation, translation = pair()
    right = verify_alignment(source, target, rotation, translation)
    assert right.verified and not right.unpinned
    unsettled = right._replace(verified=False, drift=2 * MAX_DRIFT_SPACINGS)
    assert not unsettled._replace(score=right.score._replace(constraint=0.0)).unpinned


def test_a_miss_is_judged_without_refining_it(monkeypatch):
    """An answer with too few matching points or too little overlap fails whatever it settles to: the
    check gives the verdict it would give after refining, without refining (None for its drift)."""
    source, target, rotation, translation = pair()
    clouds = AlignmentClouds(source, target)
    turned_far = turned(rotation, translation, 60.0, apply_transform(source, rotation, translation).mean(axis=0))
    misses = [(rotation, translation + 10.0), turned_far]
    refined = []
    monkeypatch.setattr(clouds, "refine", lambda *args, **kwargs: refined.append(args) or (*args[:2], 0))
    for answer in misses:
        verdict = clouds.verify(*answer)
        score = clouds.score(*answer)
        assert missed(score) is not None and verdict.drift is None and not verdict.unpinned
        assert (verdict.verified, verdict.reason) == tuple(judge(score, 0.0))
    assert refined == [], "a miss was refined"
    assert clouds.verify(rotation, translation).verified and len(refined) == 1  # a fit is refined once


def test_a_fit_below_a_stricter_bar_fails_like_a_miss():
    """`min_fitness` raises the overlap an answer needs both ways: below it, the right answer fails
    as a miss (not refined, not unpinned), and the reason names the bar."""
    source, target, rotation, translation = pair()
    clouds = AlignmentClouds(source, target)
    right = clouds.verify(rotation, translation)
    assert right.verified
    strict = clouds.verify(rotation, translation, min_fitness=min(right.score.fitness, right.score.overlap) + 0.01)
    assert not strict.verified and strict.drift is None and not strict.unpinned
    assert "low overlap" in strict.reason and "needed" in strict.reason


@pytest.mark.parametrize("method", ["PLANE_ICP", "ICP", "GICP"])
def test_refine_recovers_a_few_degrees_at_the_spacing_distance(method):
    source, target, rotation, translation = pair(jitter=0.005)
    centre = apply_transform(source, rotation, translation).mean(axis=0)
    start = turned(rotation, translation, 3.0, centre)
    refined_rotation, refined_translation, iterations = refine(source, target, *start, method=method)
    assert rotation_angle_deg(refined_rotation, rotation) < 0.5
    assert np.linalg.norm(refined_translation - translation) < 0.01
    assert iterations >= 1


def test_refinement_and_the_check_work_as_well_far_from_the_origin():
    """The same pair moved three million units out (as LiDAR scans in map coordinates are) refines to
    the same motion and passes the check, as near the origin."""
    source, target, rotation, translation = pair(jitter=0.005)
    start = turned(rotation, translation, 3.0, apply_transform(source, rotation, translation).mean(axis=0))
    offset = np.array([3e6, -2e6, 1e6])
    near = refine(source, target, *start)
    # The same motion of the moved clouds: x + offset -> R x + t + offset.
    far = refine(source + offset, target + offset, start[0], start[1] + offset - start[0] @ offset)
    assert rotation_angle_deg(far[0], near[0]) < 0.01 and rotation_angle_deg(far[0], rotation) < 0.5
    moved_near = apply_transform(source, *near[:2]) + offset
    assert np.abs(apply_transform(source + offset, *far[:2]) - moved_near).max() < 1e-4
    assert verify_alignment(source + offset, target + offset, far[0], far[1]).verified


def test_refinement_and_the_check_work_as_well_on_clouds_far_apart():
    """The target alone moved three million units out (a scan in a sensor's frame against one in a
    map's): the turns of a source centred on the target's centre lost their precision there."""
    source, target, rotation, translation = pair(jitter=0.005)
    start = turned(rotation, translation, 3.0, apply_transform(source, rotation, translation).mean(axis=0))
    offset = np.array([3e6, -2e6, 1e6])
    near = refine(source, target, *start)
    far = refine(source, target + offset, start[0], start[1] + offset)
    assert rotation_angle_deg(far[0], near[0]) < 0.01 and rotation_angle_deg(far[0], rotation) < 0.5
    assert np.abs(apply_transform(source, *far[:2]) - apply_transform(source, *near[:2]) - offset).max() < 1e-4
    assert verify_alignment(source, target + offset, far[0], far[1]).verified


def feature_shape() -> tuple[np.ndarray, np.ndarray]:
    """A lumpy ellipsoid of 4,000 points a few units across, with features to match, and a turn far
    beyond the network's reach: (points, rotation)."""
    from model.geometry import euler_to_matrix

    rng = np.random.default_rng(2)
    points = rng.normal(size=(4000, 3)) * [3.0, 2.0, 1.0] + np.sin(rng.normal(size=(4000, 1)) * [1.0, 2.0, 3.0])
    return points, euler_to_matrix([120.0, -35.0, 80.0])


def test_feature_matching_finds_any_rotation_at_any_scale():
    """KISS-Matcher refuses voxels below a few millimetres; the clouds are rescaled for it, so a
    small object in metres registers as well as a large one."""
    pytest.importorskip("kiss_matcher")
    from model.geometry import feature_match, point_spacing, rotation_angle_deg

    blob, rotation = feature_shape()
    translation = np.array([0.3, -0.1, 0.2])
    for size in (1.0, 0.005):  # a metre-sized shape, and one of a few millimetres
        source = blob * size
        target = source @ rotation.T + translation * size
        found_rotation, found_translation = feature_match(source, target, point_spacing(source))
        assert rotation_angle_deg(found_rotation, rotation) < 2.0, size
        assert np.linalg.norm(found_translation - translation * size) < 0.05 * size


def test_feature_matching_finds_the_motion_of_clouds_far_from_the_origin():
    """Clouds in map coordinates (here a million units out, a few units across) are centred for the
    matcher, whose voxel keys overflow that far out (it warned, answered wrong, and could crash)."""
    pytest.importorskip("kiss_matcher")
    from model.geometry import feature_match, point_spacing, rotation_angle_deg

    blob, rotation = feature_shape()
    offset = np.array([3e6, -2e6, 1e6])
    source = blob + offset
    translation = offset - rotation @ offset + np.array([0.3, -0.1, 0.2])  # turned about the offset, and moved
    target = source @ rotation.T + translation
    found_rotation, found_translation = feature_match(source, target, point_spacing(source))
    assert rotation_angle_deg(found_rotation, rotation) < 2.0
    assert np.linalg.norm(apply_transform(source, found_rotation, found_translation) - target, axis=1).max() < 0.5


def feature_match_in_a_process(
    folder, source: np.ndarray, target: np.ndarray, spacing: float
) -> tuple[np.ndarray, np.ndarray]:
    """feature_match's (R, t) computed in a process of its own, which must live on: a crash in
    KISS-Matcher kills its process (a segfault), which here fails the test instead of the test run."""
    import subprocess
    import sys

    np.save(folder / "source.npy", source)
    np.save(folder / "target.npy", target)
    code = (
        "import sys, numpy as np; from model.geometry import feature_match; "
        "s, t = (np.load(f'{sys.argv[1]}/{name}.npy') for name in ('source', 'target')); "
        "r, x = feature_match(s, t, float(sys.argv[2])); np.save(f'{sys.argv[1]}/found.npy', np.c_[r, x])"
    )
    done = subprocess.run(
        [sys.executable, "-c", code, str(folder), repr(spacing)], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    found = np.load(folder / "found.npy")
    return found[:, :3], found[:, 3]


def far_apart_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A scan in a sensor's frame and the same scan, turned, in a map's, three million units out:
    (source, target, rotation)."""
    source, rotation = feature_shape()
    return source, source @ rotation.T + np.array([3e6, -2e6, 1e6]), rotation


def test_feature_matching_finds_the_motion_of_clouds_far_apart_in_a_process_that_lives_on(tmp_path):
    """Moved by the target's centre, such a source still lay three million units out, where the
    matcher's keys overflow: it crashed the process (the service's worker, and the request with it)."""
    pytest.importorskip("kiss_matcher")
    from model.geometry import point_spacing

    source, target, rotation = far_apart_pair()
    found_rotation, found_translation = feature_match_in_a_process(tmp_path, source, target, point_spacing(source))
    assert rotation_angle_deg(found_rotation, rotation) < 2.0
    assert np.linalg.norm(apply_transform(source, found_rotation, found_translation) - target, axis=1).max() < 0.5


@pytest.mark.parametrize("case", ["far-apart", "a-stray-point", "near-the-origin"])
def test_feature_matching_hands_the_matcher_only_points_its_keys_reach(case, monkeypatch):
    """Every point the matcher gets lies within FEATURE_MAX_VOXELS voxels of the origin: clouds far
    apart are moved by their own centres, and a stray point no placement brings within reach (a
    thousand kilometres from a scan of a few metres) is left out; clouds within reach are not moved."""
    kiss_matcher = pytest.importorskip("kiss_matcher")
    from model.geometry import FEATURE_MAX_VOXELS, FEATURE_VOXEL, FEATURE_VOXEL_SPACINGS, feature_match, point_spacing

    given = []

    class Matcher:
        def __init__(self, config):
            pass

        def estimate(self, source, target):
            given.extend([source, target])
            return type("Found", (), {"rotation": np.eye(3), "translation": np.zeros(3)})

    monkeypatch.setattr(kiss_matcher, "KISSMatcher", Matcher)
    source, target, _ = far_apart_pair()
    if case == "a-stray-point":
        target = np.concatenate([target - target.mean(axis=0), [[1e6, 0.0, 0.0]]])
    if case == "near-the-origin":
        target = target - target.mean(axis=0)
    spacing = point_spacing(source)
    feature_match(source, target, spacing)
    scale = FEATURE_VOXEL / (FEATURE_VOXEL_SPACINGS * spacing)
    assert max(np.abs(cloud).max() for cloud in given) <= FEATURE_MAX_VOXELS * FEATURE_VOXEL
    assert [len(cloud) for cloud in given] == [len(source), len(target) - (case == "a-stray-point")]
    if case == "near-the-origin":
        assert np.allclose(given[0], source * scale) and np.allclose(given[1], target * scale)


def near_duplicate_pairs(seed: int) -> np.ndarray:
    """Points in pairs a thousandth apart, the pairs far apart: the spacing, and so feature matching's
    voxel, is the pairs' size, and no voxel has a neighbour."""
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(150, 3)) * 10
    return np.concatenate([base, base + 1e-3 * rng.normal(size=(150, 3))])


def test_feature_matching_passes_over_clouds_it_cannot_describe_instead_of_crashing(tmp_path):
    """KISS-Matcher segfaults (it killed the service's worker) on clouds whose voxels have no
    neighbours: feature matching then finds nothing, in a process that lives on."""
    pytest.importorskip("kiss_matcher")

    from model.geometry import FEATURE_VOXEL, FEATURE_VOXEL_SPACINGS, describable, point_spacing

    source, target = near_duplicate_pairs(0), near_duplicate_pairs(1)
    spacing = max(point_spacing(source), point_spacing(target))
    scale = FEATURE_VOXEL / (FEATURE_VOXEL_SPACINGS * spacing)
    assert not describable(source * scale, FEATURE_VOXEL)
    blob = np.random.default_rng(2).normal(size=(800, 3)) * [3.0, 2.0, 1.0]
    assert describable(blob * FEATURE_VOXEL / (FEATURE_VOXEL_SPACINGS * point_spacing(blob)), FEATURE_VOXEL)
    found_rotation, found_translation = feature_match_in_a_process(tmp_path, source, target, spacing)
    assert np.allclose(found_rotation, np.eye(3)) and np.allclose(found_translation, 0.0)


@pytest.mark.parametrize("far", [0.0, 1e7], ids=["one-key-per-voxel", "too-wide-for-one-key"])
def test_occupied_voxels_are_the_distinct_voxel_rows(far):
    """One int64 key per voxel, or rows where the cloud is too wide for such keys: the same voxels."""
    from model.geometry import occupied_voxels

    rng = np.random.default_rng(4)
    points = np.concatenate([rng.normal(size=(3000, 3)), rng.normal(size=(50, 3)) + far])
    found = occupied_voxels(points, 0.05)
    rows = np.unique(np.floor(points / 0.05), axis=0)
    assert np.array_equal(np.unique(found, axis=0), (rows - rows.min(axis=0)).astype(np.int64))
    assert len(found) == len(rows) < len(points)


def test_the_describable_rule_follows_kiss_matchers_normal_radius():
    kiss_matcher = pytest.importorskip("kiss_matcher")
    from model.geometry import FEATURE_NORMAL_VOXELS, FEATURE_VOXEL

    config = kiss_matcher.KISSMatcherConfig(FEATURE_VOXEL)
    assert config.normal_radius / config.voxel_size == pytest.approx(FEATURE_NORMAL_VOXELS)


def test_threads_refine_and_check_as_one_thread_does(monkeypatch):
    """small_gicp on two threads (every call of it) gives the refinement and the verdict of one."""
    import small_gicp

    source, target, rotation, translation = pair(jitter=0.005)
    start = turned(rotation, translation, 3.0, apply_transform(source, rotation, translation).mean(axis=0))
    threads_used = []
    align = small_gicp.align

    def recording(*args, **kwargs):
        threads_used.append(kwargs["num_threads"])
        return align(*args, **kwargs)

    monkeypatch.setattr(small_gicp, "align", recording)
    answers = {}
    for threads in (1, 2):
        clouds = AlignmentClouds(source, target, threads=threads)
        refined = clouds.refine(*start)
        answers[threads] = (refined, clouds.verify(*refined[:2]))
        assert set(threads_used) == {threads}
        threads_used.clear()
    (one, one_verdict), (two, two_verdict) = answers[1], answers[2]
    np.testing.assert_allclose(two[0], one[0], atol=1e-9)
    np.testing.assert_allclose(two[1], one[1], atol=1e-9)
    assert one_verdict.verified and two_verdict.verified
    assert two_verdict.drift == pytest.approx(one_verdict.drift, abs=1e-6)
