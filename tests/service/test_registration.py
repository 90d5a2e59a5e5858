"""The registration pipeline (service.registration) without HTTP: input checks, resampling,
normalisation, mapping back to user units, composition with `init`, ICP refinement.

The "model" here is an oracle that solves the normalised pair exactly by least squares on
corresponding points (the target is a rigid motion of the source, and both are resampled with
the same indices), so any error in normalising, denormalising or composing shows up directly.
"""

import asyncio
import dataclasses
import functools

import numpy as np
import pytest
from conftest import kabsch, limited_reach, pipeline_inputs

from model.geometry import (
    INLIER_SPACINGS,
    NETWORK_RADIUS,
    REFINE_SPACINGS,
    AlignmentScore,
    Verification,
    apply_transform,
    degeneracy,
    euler_to_matrix,
    farthest_point_sample,
    from_matrix,
    rotation_angle_deg,
    subset,
    to_matrix,
)
from service.batcher import Prediction
from service.registration import (
    STARTS_POINTS,
    CloudSampler,
    Network,
    RegistrationFailed,
    RegistrationResult,
    register_clouds,
)
from service.schemas import RefineOptions
from service.validation import InvalidInput, as_points, as_rigid_transform

# Float32 rounding of the network's input is the only error the oracle leaves.
ROTATION_TOLERANCE_DEG = 1e-5
TRANSLATION_TOLERANCE = 1e-7  # times the cloud's radius

TRUE_ROTATION = euler_to_matrix([40.0, 25.0, -30.0])
TRUE_TRANSLATION = np.array([2.0, -1.5, 0.3])  # metres
INIT = to_matrix(euler_to_matrix([10.0, 0.0, 5.0]), np.array([0.5, 0.2, 0.0]))


async def oracle(source: np.ndarray, target: np.ndarray) -> Prediction:
    assert source.dtype == np.float32 and target.dtype == np.float32
    # The network's input contract: each cloud centred, the larger one reaching NETWORK_RADIUS.
    for cloud in (source, target):
        assert np.abs(cloud.mean(axis=0)).max() < 1e-5
        assert np.linalg.norm(cloud, axis=1).max() <= NETWORK_RADIUS + 1e-6
    assert max(np.linalg.norm(source, axis=1).max(), np.linalg.norm(target, axis=1).max()) >= NETWORK_RADIUS - 1e-5
    return Prediction(*kabsch(source.astype(np.float64), target.astype(np.float64)))


def register(source, target, network_points, predict=oracle, **options):
    return asyncio.run(register_clouds(source, target, *pipeline_inputs(network_points, predict, **options)))


def radius(points: np.ndarray) -> float:
    return float(np.linalg.norm(points - points.mean(axis=0), axis=1).max())


@pytest.mark.parametrize(
    ("scan", "sampling"),
    [
        ("pcl_bunny_view0", "fps"),  # 397 points: upsampled to 768
        ("kitti_000008_fov", "fps"),  # 17k lidar points in metres
        ("nuscenes_lidar_top", "random"),  # 35k points with 3,469 exact duplicates
        ("pcl_office1", "random"),  # 254k points
    ],
)
def test_known_transform_is_recovered_on_real_scans(real_scans, scan, sampling):
    source = real_scans[scan]
    target = apply_transform(source, TRUE_ROTATION, TRUE_TRANSLATION)
    result = register(source, target, 768, sampling=sampling, seed=3, init=INIT)

    assert rotation_angle_deg(result.rotation, TRUE_ROTATION) < ROTATION_TOLERANCE_DEG
    assert np.linalg.norm(result.translation - TRUE_TRANSLATION) < TRANSLATION_TOLERANCE * radius(source)
    np.testing.assert_allclose(result.transform, to_matrix(result.rotation, result.translation))
    assert result.fitness == 1.0 and result.inlier_rmse < 1e-6 * radius(source)
    distinct = len(np.unique(source, axis=0))
    assert result.points.source.received == len(source)
    assert result.points.source.duplicates_removed == len(source) - distinct
    assert result.points.source.network_points == 768 and result.points.source.upsampled == (distinct < 768)


def test_without_init_and_with_other_network_sizes(real_scans):
    source = real_scans["pcl_bunny_view4"]
    target = apply_transform(source, TRUE_ROTATION, TRUE_TRANSLATION)
    for count in (64, 1024):
        result = register(source, target, count)
        assert result.points.source.network_points == count
        assert rotation_angle_deg(result.rotation, TRUE_ROTATION) < ROTATION_TOLERANCE_DEG
        assert np.linalg.norm(result.translation - TRUE_TRANSLATION) < TRANSLATION_TOLERANCE * radius(source)


def test_the_answer_does_not_depend_on_units(real_scans):
    """Millimetres instead of metres: same rotation, translation 1000 times larger."""
    source = real_scans["pcl_bunny_view0"]
    target = apply_transform(source, TRUE_ROTATION, TRUE_TRANSLATION)
    metres = register(source, target, 256)
    millimetres = register(source * 1000.0, target * 1000.0, 256)
    np.testing.assert_allclose(millimetres.rotation, metres.rotation, atol=1e-6)
    np.testing.assert_allclose(millimetres.translation, metres.translation * 1000.0, rtol=1e-6, atol=1e-6)
    assert millimetres.fitness_threshold == pytest.approx(metres.fitness_threshold * 1000.0)


def test_refinement_corrects_a_network_error_in_user_units(real_scans):
    """The "network" is 3 degrees and 3% of the radius off; ICP on the full clouds fixes it."""
    source = real_scans["kitti_000008_fov"]
    rng = np.random.default_rng(0)
    noise = rng.normal(scale=1e-4 * radius(source), size=source.shape)
    target = apply_transform(source, TRUE_ROTATION, TRUE_TRANSLATION) + noise
    error_rotation = euler_to_matrix([3.0, 0.0, 0.0])

    async def three_degrees_off(source_n, target_n):
        exact = await oracle(source_n, target_n)
        return Prediction(error_rotation @ exact.rotation, exact.translation + [0.03, 0.0, 0.0])

    result = register(source, target, 768, three_degrees_off, sampling="random", refine=RefineOptions())
    network_error = rotation_angle_deg(from_matrix(result.refinement.network_transform)[0], TRUE_ROTATION)
    assert 2.9 < network_error < 3.1
    assert rotation_angle_deg(result.rotation, TRUE_ROTATION) < 0.01
    assert np.linalg.norm(result.translation - TRUE_TRANSLATION) < 1e-4 * radius(source)
    # The default correspondence distance and the inlier distance both follow the clouds' point spacing.
    spacing = result.fitness_threshold / INLIER_SPACINGS
    assert result.refinement.max_distance == pytest.approx(REFINE_SPACINGS * spacing)
    assert result.verified and result.reason is None and result.stage == "ifnet"
    assert result.refinement.iterations >= 1
    assert result.fitness > 0.99


def test_the_global_paths_starts_run_on_fewer_points_and_still_find_the_turn(real_scans, monkeypatch):
    """Feature matching is made to fail, so the 24 rotated starts run: on STARTS_POINTS points per
    cloud (a coarse answer each, which refinement settles), and the right start wins."""
    from service import registration

    monkeypatch.setattr(registration, "feature_match", lambda *args: (np.eye(3), np.zeros(3)))
    shapes = []

    async def recorded(source_n, target_n):  # the oracle's answer, without its check of a whole cloud's centring
        shapes.append((source_n.shape, target_n.shape))
        return Prediction(*kabsch(source_n.astype(np.float64), target_n.astype(np.float64)))

    source = real_scans["kitti_000008_fov"]
    target = apply_transform(source, euler_to_matrix([150.0, 40.0, -70.0]), TRUE_TRANSLATION)
    result = register(source, target, 768, recorded, method="global")
    starts = registration.STARTS_POINTS
    assert shapes == [((starts, 3), (starts, 3))] * 24
    assert result.stage == "multistart" and result.verified
    assert rotation_angle_deg(result.rotation, euler_to_matrix([150.0, 40.0, -70.0])) < 0.01


def recording(asked: list, name: str, turn=None):
    """An oracle that records (name, points per cloud) in `asked` at each call; `turn` spoils its answer."""

    async def predict(source_n, target_n):
        asked.append((name, len(source_n)))
        rotation, translation = kabsch(source_n.astype(np.float64), target_n.astype(np.float64))
        rotation = rotation if turn is None else turn @ rotation
        return Prediction(rotation, translation, inference_ms=1.0, batch_size=1)

    return predict


def auto_with_draft(source: np.ndarray, target: np.ndarray, draft_turn=None) -> tuple[RegistrationResult, list]:
    """`auto` on the pair with an oracle model and its draft (`recording`; `draft_turn` spoils the
    draft's answers): the answer, and the calls asked, in order."""
    asked = []
    options, settings, _ = pipeline_inputs(None, None, method="auto")
    draft = Network("object", 384, recording(asked, "draft", draft_turn), "draft")
    networks = [Network("object", 768, recording(asked, "model"), draft=draft)]
    return asyncio.run(register_clouds(source, target, options, settings, networks)), asked


def test_auto_asks_the_draft_first_and_keeps_its_answer_only_where_feature_matching_agrees(real_scans, monkeypatch):
    """A model with a draft: `auto` asks the draft (at its points, refining its answer even unasked)
    and stops there when feature matching's guess agrees; when it does not (a draft answer far from
    the guess is not even refined), the guess is refined and checked and, where it fails, the model
    is asked as if there were no draft; the other models' drafts are not asked. The 24 rotated
    starts, which judge a verified answer past the draft, ask the first model's draft, under
    `global` too; `ifnet` asks the model alone."""
    from service import registration

    asked = []
    recorded = functools.partial(recording, asked)

    def run(method, target, first_turned=False):
        options, settings, _ = pipeline_inputs(None, None, method=method)
        turn = euler_to_matrix([90.0, 0.0, 0.0]) if first_turned else None
        draft = Network("object", 384, recorded("draft", turn), "draft")
        other_draft = Network("indoor", 384, recorded("indoor draft"), "draft")
        networks = [Network("object", 768, recorded("model", turn), draft=draft)]
        networks.append(Network("indoor", 768, recorded("indoor"), draft=other_draft))
        asked.clear()
        return asyncio.run(register_clouds(source, target, options, settings, networks))

    source = real_scans["kitti_000008_fov"]
    target = apply_transform(source, TRUE_ROTATION, TRUE_TRANSLATION)
    confirmed = run("auto", target)
    assert asked == [("draft", 384)] and (confirmed.stage, confirmed.verified) == ("draft", True)
    assert confirmed.refinement is not None  # a draft's answer is always refined
    assert rotation_angle_deg(confirmed.rotation, TRUE_ROTATION) < 0.01

    far = TRUE_TRANSLATION + 10.0 * radius(source)  # no turn, and far off: refined, it fails the check
    monkeypatch.setattr(registration, "feature_match", lambda *args: (np.eye(3), far))  # disagrees
    checked, check = [], registration._checked
    monkeypatch.setattr(registration, "_checked", lambda *args: checked.append(args[1]) or check(*args))
    unconfirmed = run("auto", target)
    # The guess (no turn) would ask the draft the same question again: it is not asked twice.
    starts = [("draft", registration.STARTS_POINTS)] * 24
    assert asked == [("draft", 384), ("model", 768), *starts]
    assert (unconfirmed.stage, unconfirmed.verified) == ("ifnet", True)
    # The draft's answer, more than DRAFT_REACH_DEG from the guess, was set aside unrefined: the
    # guess (matched on the check's subset, then on more points: a large scan) and then the model's
    # answer were refined and checked; the starts all landed on the answer.
    assert len(checked) == 3
    assert all(rotation_angle_deg(guess, np.eye(3)) == pytest.approx(0.0, abs=1e-9) for guess in checked[:2])
    assert unconfirmed.timings_ms["inference_ms"] == 26.0  # the discarded draft's call and the starts' were paid for
    other = run("auto", target, first_turned=True)  # only the first model's draft is asked
    assert asked == [("draft", 384), ("model", 768), ("indoor", 768), *starts]
    assert (other.model, other.verified) == ("indoor", True)
    searched = run("global", apply_transform(source, euler_to_matrix([150.0, 40.0, -70.0]), TRUE_TRANSLATION))
    assert asked == starts and searched.stage == "multistart"
    network = run("ifnet", target)
    assert asked == [("model", 768)] and (network.stage, network.refinement) == ("ifnet", None)


def test_under_auto_only_candidates_may_skip_the_fine_pass(real_scans, monkeypatch):
    """Under `auto`, with nothing verified to judge, the draft's and the models' answers are candidates
    of the search: refined, they may skip the fine pass (FINE_PASS_MIN_FITNESS); where the draft's
    verified answer waits to be judged, the models' answers judge it and get every pass, as does the
    answer `ifnet` gives."""
    from service import registration

    asked, finished, finish = [], [], registration._finish
    monkeypatch.setattr(
        registration, "_finish", lambda *args: finished.append((args[2].stage, args[-1])) or finish(*args)
    )

    def shifted(name: str):
        """An oracle whose translation lands 5 cloud radii off, in the network's frame: it fits nothing."""
        predict = recording(asked, name)

        async def off(source_n, target_n):
            prediction = await predict(source_n, target_n)
            return dataclasses.replace(prediction, translation=prediction.translation + 5.0)

        return off

    def run(method, draft_predict, guess_turn):
        monkeypatch.setattr(registration, "feature_match", lambda *args: (guess_turn @ TRUE_ROTATION, far))
        options, settings, _ = pipeline_inputs(None, None, method=method)
        networks = [
            Network("object", 768, recording(asked, "model"), draft=Network("object", 384, draft_predict, "draft"))
        ]
        finished.clear()
        return asyncio.run(register_clouds(source, target, options, settings, networks))

    source = real_scans["kitti_000008_fov"]
    target = apply_transform(source, TRUE_ROTATION, TRUE_TRANSLATION)
    far = TRUE_TRANSLATION + 10.0 * radius(source)  # the guess's turn, but far off: it fails the check
    bar = registration.FINE_PASS_MIN_FITNESS
    searched = run("auto", shifted("draft"), np.eye(3))
    # The draft asked as the source lies and turned by the guess, both off; then the model.
    assert finished == [("draft", bar), ("draft", bar), ("ifnet", bar)]
    assert (searched.stage, searched.verified) == ("ifnet", True)
    judged = run("auto", recording(asked, "draft"), euler_to_matrix([10.0, 0.0, 0.0]))
    # The draft's verified answer, 10 deg from the guess, is not confirmed: the model judges it.
    assert finished == [("draft", bar), ("ifnet", 0.0)] and judged.verified
    assert run("ifnet", shifted("draft"), np.eye(3)).stage == "ifnet" and finished == [("ifnet", 0.0)]


@pytest.mark.parametrize("points", [None, 6_000], ids=["thinned scan", "whole"])
def test_where_the_draft_fails_a_verified_guess_spares_the_models(real_scans, points):
    """`auto` past an unconfirmed draft: feature matching's answer, refined and verified, is judged
    by the rotated starts or, on a scan thinned for the check, by its half turns, and no model is
    asked."""
    from service import registration

    source = real_scans["kitti_000008_fov"]
    source = source if points is None else subset(source, points)
    target = apply_transform(source, TRUE_ROTATION, TRUE_TRANSLATION)
    turn = euler_to_matrix([90.0, 0.0, 0.0])  # every draft answer far from the (right) guess
    result, asked = auto_with_draft(source, target, turn)
    thinned = len(source) > registration.CHECK_MAX_POINTS
    starts = [] if thinned else [("draft", STARTS_POINTS)] * 24
    assert asked == [("draft", 384), ("draft", 384), *starts]  # as it lies, at the guess's turn, the starts
    assert (result.stage, result.verified) == ("features", True)
    assert rotation_angle_deg(result.rotation, TRUE_ROTATION) < 0.01


@pytest.mark.parametrize("truth_deg", [[20.0, 10.0, 0.0], [150.0, 40.0, -70.0]], ids=["within reach", "beyond"])
def test_the_draft_is_asked_again_only_where_the_guess_turns_the_source_beyond_its_reach(
    real_scans, monkeypatch, truth_deg
):
    """The draft's first answer is 90 deg off. Where feature matching's guess turns the source within
    NETWORK_REACH_DEG, the draft already saw the source within its reach of that turn: it is not asked
    again, and the guess refined is the answer. Beyond it, the draft is asked for the source turned by
    the guess."""
    from service import registration

    truth = euler_to_matrix(truth_deg)
    monkeypatch.setattr(registration, "feature_match", lambda *args: (truth, TRUE_TRANSLATION))
    source = real_scans["kitti_000008_fov"]  # thinned for the check: no rotated start asks the draft
    target = apply_transform(source, truth, TRUE_TRANSLATION)
    result, asked = auto_with_draft(source, target, euler_to_matrix([90.0, 0.0, 0.0]))
    within = rotation_angle_deg(truth, np.eye(3)) <= registration.NETWORK_REACH_DEG
    assert asked == [("draft", 384)] * (1 if within else 2)
    assert (result.stage, result.verified) == ("features", True)
    assert rotation_angle_deg(result.rotation, truth) < 0.01


def steps_of_auto(source: np.ndarray, target: np.ndarray, threads: int) -> tuple[list, RegistrationResult]:
    """`auto` with a draft that can start a call beside feature matching: the steps run through
    run_blocking, the calls started beside and the draft's other calls, in order."""
    events = []
    beside = recording([], "draft")

    async def start_beside(source_n, target_n):
        events.append("draft started beside")
        return asyncio.ensure_future(beside(source_n, target_n))

    async def run_blocking(function, *args):
        events.append(function.__name__)
        return function(*args)

    options, settings, _ = pipeline_inputs(None, None, method="auto")
    draft = Network("object", 384, recording(events, "draft"), "draft", start_beside=start_beside)
    networks = [Network("object", 768, recording(events, "model"), draft=draft)]
    return events, asyncio.run(register_clouds(source, target, options, settings, networks, run_blocking, threads))


def test_a_lone_requests_draft_call_is_under_way_before_feature_matching_starts(real_scans):
    """`auto` alone in its worker (all its threads) starts the draft's call for the source as it lies
    (start_beside: on fewer threads, returning once a thread runs it) before feature matching, which
    runs beside it, and does not make that call again. Among other requests (one thread) the call
    waits for feature matching, as it would wait its turn in the queue anyway."""
    source = real_scans["kitti_000008_fov"]
    target = apply_transform(source, TRUE_ROTATION, TRUE_TRANSLATION)
    alone, result = steps_of_auto(source, target, threads=2)
    assert alone[:3] == ["_prepare", "draft started beside", "_feature_guess"]
    assert ("draft", 384) not in alone and (result.stage, result.verified) == ("draft", True)
    among_others, result = steps_of_auto(source, target, threads=1)
    assert among_others[:3] == ["_prepare", "_feature_guess", ("draft", 384)]
    assert "draft started beside" not in among_others and (result.stage, result.verified) == ("draft", True)


def test_a_verified_draft_answer_the_guess_is_too_coarse_to_confirm_is_confirmed_by_the_guess_refined(
    real_scans, monkeypatch
):
    """Feature matching's guess 7 deg off (as on noisy clouds): refined and checked, it lands on the
    draft's verified answer, which then stands without the model being asked; its cost is counted."""
    from service import registration

    coarse = euler_to_matrix([7.0, 0.0, 0.0]) @ TRUE_ROTATION
    monkeypatch.setattr(registration, "feature_match", lambda *args: (coarse, TRUE_TRANSLATION))
    asked = []
    draft = Network("object", 384, recording(asked, "draft"), "draft")
    options, settings, _ = pipeline_inputs(None, None, method="auto")
    networks = [Network("object", 768, recording(asked, "model"), draft=draft)]
    source = real_scans["kitti_000008_fov"]
    result = asyncio.run(
        register_clouds(source, apply_transform(source, TRUE_ROTATION, TRUE_TRANSLATION), options, settings, networks)
    )
    assert asked == [("draft", 384)] and (result.stage, result.verified) == ("draft", True)
    assert rotation_angle_deg(result.rotation, TRUE_ROTATION) < 0.01

    off = euler_to_matrix([25.0, 0.0, 0.0]) @ TRUE_ROTATION, TRUE_TRANSLATION + 50.0  # within reach, but wrong
    monkeypatch.setattr(registration, "feature_match", lambda *args: off)
    asked.clear()
    checked, check = [], registration._checked
    monkeypatch.setattr(registration, "_checked", lambda *args: checked.append(args[1]) or check(*args))
    other = asyncio.run(
        register_clouds(source, apply_transform(source, TRUE_ROTATION, TRUE_TRANSLATION), options, settings, networks)
    )
    # The refined guess lands elsewhere: the model is asked, and the guess is not refined a second time
    # (the draft's answer, the guess, the guess matched again on more points of this large scan, and
    # the model's answer are checked; the starts land on the answer).
    starts = [("draft", registration.STARTS_POINTS)] * 24
    assert asked == [("draft", 384), ("model", 768), *starts] and (other.stage, other.verified) == ("ifnet", True)
    assert len(checked) == 4


def test_auto_asks_the_draft_again_from_feature_matchings_guess_for_a_turn_beyond_its_reach(real_scans, monkeypatch):
    """A pair turned 150 deg: the draft, asked for the source as it lies, answers far from the
    guess; asked again for the source turned by the guess (3 deg off), it gives the answer, refined
    and confirmed. Its first answer fits too poorly to contradict it: it is not even refined, but its
    call is paid for. The model is not asked."""
    from service import registration

    truth = euler_to_matrix([150.0, 40.0, -70.0])
    guess = euler_to_matrix([3.0, 0.0, 0.0]) @ truth
    monkeypatch.setattr(registration, "feature_match", lambda *args: (guess, TRUE_TRANSLATION))
    checked, check = [], registration._checked
    monkeypatch.setattr(registration, "_checked", lambda *args: checked.append(args[1]) or check(*args))
    turns, model_turns = [], []
    options, settings, _ = pipeline_inputs(None, None, method="auto", init=INIT)
    draft = Network("object", 384, limited_reach(turns), "draft")
    networks = [Network("object", 768, limited_reach(model_turns), draft=draft)]
    source = real_scans["kitti_000008_fov"]
    target = apply_transform(source, truth, TRUE_TRANSLATION)
    result = asyncio.run(register_clouds(source, target, options, settings, networks))
    assert len(turns) == 2 and turns[0] > 45.0 and turns[1] == pytest.approx(3.0, abs=0.01) and model_turns == []
    assert (result.stage, result.verified) == ("draft", True)
    assert rotation_angle_deg(result.rotation, truth) < 0.01
    assert len(checked) == 1 and rotation_angle_deg(checked[0], truth) < 10.0  # only the answer from the guess's turn
    assert result.timings_ms["inference_ms"] == 2.0


@pytest.mark.parametrize("margin", [None, 1e9], ids=["rule", "without it"])
@pytest.mark.parametrize("guess_deg", [-1.9, 1.0], ids=["guess 5.6 deg away", "guess 2.7 deg away"])
def test_a_draft_answer_the_refined_guess_fits_clearly_better_than_is_not_confirmed(
    real_scans, monkeypatch, margin, guess_deg
):
    """The draft's verified answer, fitting 0.30, lies 5.6 or 2.7 deg from feature matching's guess;
    the guess refined is verified, 3.7 deg from it, and fits 0.2 better (the draft's answer sat in a
    local minimum beside the truth, as on a TUM room view): that confirms nothing, and the better
    fitting answer is the request's. Even a guess within AGREEMENT_DEG does not confirm an answer
    fitting that little as it is. Refinement and the check are stand-ins here that settle each pose
    on one of the two."""
    from service import registration

    if margin is not None:
        monkeypatch.setattr(registration, "CONFIRMING_BETTER_FIT", margin)
        monkeypatch.setattr(registration, "UNCORROBORATED_MIN_FITNESS", 0.0)  # the other net under a 0.30 fit
    beside = euler_to_matrix([3.7, 0.0, 0.0]) @ TRUE_ROTATION
    guess = euler_to_matrix([guess_deg, 0.0, 0.0]) @ TRUE_ROTATION
    monkeypatch.setattr(registration, "feature_match", lambda *args: (guess, TRUE_TRANSLATION))

    def settled(prepared, rotation, translation, refine_options, min_fitness=None, fine_bar=0.0):
        local = rotation_angle_deg(rotation, beside) < 1.0
        fitness = 0.30 if local else 0.50
        score = AlignmentScore(0.01, 0.015, fitness, 0.005, fitness, int(1000 * fitness), 0.1)
        pose = beside if local else TRUE_ROTATION
        return registration._Candidate(pose, TRUE_TRANSLATION, None, Verification(True, None, score, 0.0))

    monkeypatch.setattr(registration, "_checked", settled)
    source = real_scans["kitti_000008_fov"]
    target = apply_transform(source, TRUE_ROTATION, TRUE_TRANSLATION)
    options, settings, _ = pipeline_inputs(None, None, method="auto")
    draft = Network("object", 384, recording([], "draft", beside @ TRUE_ROTATION.T), "draft")
    networks = [Network("object", 768, recording([], "model"), draft=draft)]
    result = asyncio.run(register_clouds(source, target, options, settings, networks))
    assert result.verified
    if margin is None:
        assert result.stage == "features" and rotation_angle_deg(result.rotation, TRUE_ROTATION) < 0.01
    else:
        assert result.stage == "draft" and rotation_angle_deg(result.rotation, beside) < 0.01


@pytest.mark.parametrize("corroborated", [True, False])
def test_the_rotated_starts_judge_a_verified_answer_refining_only_rivals_that_fit(
    real_scans, monkeypatch, corroborated
):
    """A verified model answer on a real scan: the 24 rotated starts judge it (asked of the model,
    which has no draft). Those within the network's reach land on the answer; the others, far from
    it, fit too poorly to be rivals: none is refined but the best of them (STARTS_JUDGING_ANYWAY),
    and the answer stands. Where feature matching's guess is far off (refined, it fails the check),
    nothing corroborates the answer and the best UNCORROBORATED_JUDGING_ANYWAY are refined."""
    from service import registration

    truth = euler_to_matrix([20.0, 10.0, 5.0])  # within the network's reach
    guess = truth if corroborated else euler_to_matrix([150.0, 0.0, 0.0])
    monkeypatch.setattr(registration, "feature_match", lambda *args: (guess, TRUE_TRANSLATION))
    checked, check = [], registration._checked
    monkeypatch.setattr(registration, "_checked", lambda *args: checked.append(args[1]) or check(*args))
    turns = []
    options, settings, _ = pipeline_inputs(None, None, method="auto")
    source = real_scans["kitti_000008_fov"]
    target = apply_transform(source, truth, TRUE_TRANSLATION)
    networks = [Network("object", 768, limited_reach(turns))]
    result = asyncio.run(register_clouds(source, target, options, settings, networks))
    assert (result.stage, result.verified) == ("ifnet", True) and len(turns) == 1 + 24
    # Uncorroborated, the guess was refined and checked too.
    judged = registration.STARTS_JUDGING_ANYWAY if corroborated else 1 + registration.UNCORROBORATED_JUDGING_ANYWAY
    assert len(checked) == 1 + judged and result.timings_ms["inference_ms"] == 25.0


def test_a_draft_answer_from_the_guess_does_not_stand_where_its_own_answer_contradicts_it(monkeypatch):
    """A box sampled symmetrically is the same turned 180 deg about an axis. Feature matching's
    guess is that flip of the truth; the draft, asked for the source turned by the guess, stays
    there (it fits perfectly). Its own answer, the truth, refined, fits as well: the clouds do not
    tell which is right, so the draft's answer does not stand and the answer is flagged as
    ambiguous, without asking the model (a third answer cannot unmake two that fit)."""
    from service import registration

    rng = np.random.default_rng(5)
    sides = np.array([2.0, 1.0, 0.5])
    faces = rng.integers(0, 3, 3000)
    points = rng.uniform(-0.5, 0.5, (3000, 3)) * sides
    points[np.arange(3000), faces] = np.sign(rng.uniform(-1, 1, 3000)) * sides[faces] / 2  # on the box's faces
    points = np.concatenate([points, points * [-1.0, -1.0, 1.0]])  # each point's twin half a turn about z
    truth = euler_to_matrix([20.0, 10.0, 0.0])
    flip = truth @ euler_to_matrix([180.0, 0.0, 0.0])  # about the box's z axis: the same box
    monkeypatch.setattr(registration, "feature_match", lambda *args: (flip, np.zeros(3)))
    asked = []

    async def stays_when_turned(source_n, target_n):
        asked.append("draft")
        if len(asked) == 2:  # from the guess: already fitting, it stays
            return Prediction(np.eye(3), np.zeros(3))
        return Prediction(*kabsch(source_n.astype(np.float64), target_n.astype(np.float64)))

    async def model(source_n, target_n):
        asked.append("model")
        return Prediction(*kabsch(source_n.astype(np.float64), target_n.astype(np.float64)))

    options, settings, _ = pipeline_inputs(None, None, method="auto")
    networks = [Network("object", 768, model, draft=Network("object", 384, stays_when_turned, "draft"))]
    result = asyncio.run(
        register_clouds(points, apply_transform(points, truth, np.zeros(3)), options, settings, networks)
    )
    assert asked == ["draft", "draft"]
    assert not result.verified and result.reason.startswith("ambiguous")


def table_top(rng: np.random.Generator) -> np.ndarray:
    """A wide table with a low box on it: most matching points lie on one plane, so a right answer
    fits and settles but fails the check on its constraint (unpinned), as on indoor crops."""
    table = np.column_stack([rng.uniform(-1.0, 1.0, (5000, 2)), np.zeros(5000)])
    box = rng.uniform([-0.1, -0.1, 0.0], [0.1, 0.1, 0.02], (100, 3))
    return np.concatenate([table, box])


TABLE_VIEWS_TURN = euler_to_matrix([20.0, 5.0, -5.0])


def table_views_answer(monkeypatch, match) -> tuple[RegistrationResult, list, np.ndarray]:
    """`auto` on two views of a large table with a low box on it (thinned for the check), each seeing
    about 2/3 of it (a right answer matches about half the source and fails the check on its
    constraint), the second moved by TABLE_VIEWS_TURN, with `match` as feature matching and oracle
    draft (its answers 90 deg off: far from any guess) and model (`recording`): the answer, the calls
    asked, the source."""
    from service import registration

    rng = np.random.default_rng(4)
    table = np.column_stack([rng.uniform(-1.5, 1.5, (24_000, 2)), np.zeros(24_000)])
    scene = np.concatenate([table, rng.uniform([-0.1, -0.1, 0.0], [0.1, 0.1, 0.02], (400, 3))])
    source, view = scene[scene[:, 0] < 0.5], scene[scene[:, 0] > -0.5]
    monkeypatch.setattr(registration, "feature_match", match)
    target = apply_transform(view, TABLE_VIEWS_TURN, np.zeros(3))
    return *auto_with_draft(source, target, euler_to_matrix([90.0, 0.0, 0.0])), source


def tabletop_answer(monkeypatch, guess_turn_deg: float):
    """`auto` on the table top moved by a known turn, with feature matching's guess `guess_turn_deg`
    off it and oracle draft and model (`recording`): the answer, the calls asked, the true rotation."""
    from service import registration

    points = table_top(np.random.default_rng(3))
    truth = euler_to_matrix([20.0, 5.0, -5.0])
    guess = euler_to_matrix([guess_turn_deg, 0.0, 0.0]) @ truth
    monkeypatch.setattr(registration, "feature_match", lambda *args: (guess, np.zeros(3)))
    asked = []
    options, settings, _ = pipeline_inputs(None, None, method="auto")
    draft = Network("object", 384, recording(asked, "draft"), "draft")
    networks = [
        Network("object", 768, recording(asked, "model"), draft=draft),
        Network("indoor", 768, recording(asked, "indoor")),
    ]
    target = apply_transform(points, truth, np.zeros(3))
    return asyncio.run(register_clouds(points, target, options, settings, networks)), asked, truth


@pytest.mark.parametrize(("guess_turn_deg", "stands"), [(2.0, True), (90.0, False)])
def test_an_unpinned_draft_answer_stands_unverified_where_feature_matching_agrees(monkeypatch, guess_turn_deg, stands):
    """The draft's answer fails the check only because the clouds let it slide. Where feature
    matching's guess agrees with it in turn and translation, it is the answer, not verified, without
    refining the guess, and no model is asked: any answer near it would fail alike. Where the guess
    disagrees, the pipeline goes on to the model."""
    from service import registration

    refined = []
    finish_features = registration._finish_features
    monkeypatch.setattr(registration, "_finish_features", lambda *args: refined.append(1) or finish_features(*args))
    result, asked, truth = tabletop_answer(monkeypatch, guess_turn_deg)
    if stands:
        assert (result.stage, result.verified, asked, refined) == ("draft", False, [("draft", 384)], [])
        assert "pin" in result.reason and rotation_angle_deg(result.rotation, truth) < 0.5
    else:
        assert ("model", 768) in asked


@pytest.mark.parametrize("fitness_needed", [0.85, 1.01], ids=["matches-most", "matches-less"])
def test_an_unpinned_answer_matching_most_of_the_source_ends_the_search(monkeypatch, fitness_needed):
    """Feature matching's guess disagrees with the draft's unpinned answer, so the model is asked: its
    answer, right, fails the check only on its constraint and matches the whole source. Under `auto`
    neither the next model nor the rotated starts search then (on tabletops they only added answers
    pinned no better, or flips fitting a little better); where the answer matches less than
    UNPINNED_FITNESS of the source, they do."""
    from service import registration

    monkeypatch.setattr(registration, "UNPINNED_FITNESS", fitness_needed)
    result, asked, truth = tabletop_answer(monkeypatch, 90.0)
    searched = asked.count(("draft", 384)) >= len(registration.STARTS)
    assert ("model", 768) in asked and not result.verified and "pin" in result.reason
    assert searched == (fitness_needed > 1.0) and (("indoor", 768) in asked) == searched
    if not searched:
        assert result.stage == "ifnet" and rotation_angle_deg(result.rotation, truth) < 0.5


@pytest.mark.parametrize("fitness_needed", [0.4, 0.9], ids=["matches-enough", "matches-less"])
def test_on_a_thinned_scan_an_unpinned_answer_matching_less_also_ends_the_search(monkeypatch, fitness_needed):
    """Two overlapping views of a large table top (thinned for the check): feature matching's answer,
    right, fails the check only on its constraint and matches about half the source. There
    UNPINNED_FITNESS_THINNED, not UNPINNED_FITNESS, ends the search: no model and no rotated start is
    asked where the answer matches that much; where it matches less, they are."""
    from service import registration

    monkeypatch.setattr(registration, "UNPINNED_FITNESS_THINNED", fitness_needed)
    truth = TABLE_VIEWS_TURN
    result, asked, _ = table_views_answer(monkeypatch, lambda *args: (truth, np.zeros(3)))
    assert not result.verified and "pin" in result.reason and 0.4 < result.score.fitness < 0.9
    ended = fitness_needed < result.score.fitness
    assert (("model", 768) not in asked) == ended and (len(asked) < len(registration.STARTS)) == ended
    if ended:
        assert result.stage == "features" and rotation_angle_deg(result.rotation, truth) < 0.5


def test_a_start_replaces_an_unpinned_answer_only_where_it_fits_clearly_better(monkeypatch):
    """Where the rotated starts search past an unpinned answer (the right one, on a tabletop), an
    unverified start fitting less than RIVAL_FITNESS_MARGIN better (the table flipped) is left out;
    one fitting clearly better, or verified, stays a candidate."""
    import dataclasses

    from service import registration

    points = table_top(np.random.default_rng(3))
    truth = euler_to_matrix([20.0, 5.0, -5.0])
    target = apply_transform(points, truth, np.zeros(3))
    options, settings, _ = pipeline_inputs(None, None, method="auto", refine={})
    prepared = registration._prepare(points, target, 384, options, settings)
    checked = registration._checked(prepared, truth, np.zeros(3), options.refine)
    right = registration._result(prepared, checked, "ifnet", "object", options, dict(registration._FREE))
    assert right.unpinned and not right.verified
    flip = euler_to_matrix([0.0, 0.0, 180.0]) @ truth  # half a turn about the table's normal

    def start(better_by: float, verified: bool = False):
        score = right.score._replace(fitness=right.score.fitness - 0.2 + better_by)
        return dataclasses.replace(right, rotation=flip, stage="multistart", score=score, verified=verified)

    lower = dataclasses.replace(right, score=right.score._replace(fitness=right.score.fitness - 0.2))
    close, clear, verified = start(0.02), start(0.1), start(0.0, verified=True)
    kept = registration._fitting_clearly_better([close, clear, verified], [lower])
    assert kept == [clear, verified]
    assert registration._fitting_clearly_better([close], [dataclasses.replace(lower, unpinned=False)]) == [close]


def test_an_unpinned_draft_answer_slid_from_the_truth_gives_way_to_feature_matchings_pinned_one(monkeypatch):
    """A floor and two walls meeting in a corner: the truth lays the corners on each other (pinned);
    a pose slid along one wall matches the floor and that wall alone (unpinned). The draft answers
    the truth's turn, slid; feature matching's guess, the truth, refined, is pinned and verified: the
    slid answer does not stand though its turn agrees with the guess, and feature matching's does."""
    from service import registration

    rng = np.random.default_rng(4)
    floor = np.column_stack([rng.uniform(0, 4, 6000), rng.uniform(0, 2, 6000), np.zeros(6000)])
    wall = np.column_stack([rng.uniform(0, 4, 3000), np.zeros(3000), rng.uniform(0, 1, 3000)])
    end = np.column_stack([np.zeros(1500), rng.uniform(0, 2, 1500), rng.uniform(0, 1, 1500)])
    points = np.concatenate([floor, wall, end])
    truth = euler_to_matrix([20.0, 5.0, -5.0])
    monkeypatch.setattr(registration, "feature_match", lambda *args: (truth, np.zeros(3)))

    async def slid(source_n, target_n):  # the truth's turn, slid along the wall (half a normalised unit)
        rotation, translation = kabsch(source_n.astype(np.float64), target_n.astype(np.float64))
        return Prediction(rotation, translation + rotation @ [0.5, 0.0, 0.0])

    options, settings, _ = pipeline_inputs(None, None, method="auto")
    networks = [Network("object", 768, slid, draft=Network("object", 384, slid, "draft"))]
    target = apply_transform(points, truth, np.zeros(3))
    result = asyncio.run(register_clouds(points, target, options, settings, networks))
    assert (result.stage, result.verified) == ("features", True)
    assert np.linalg.norm(result.translation) < 0.01 and rotation_angle_deg(result.rotation, truth) < 0.1


@pytest.mark.parametrize("scan", ["pcl_table_scene_mug", "sunrgbd_000017"])
def test_feature_matching_finds_the_motion_of_two_samples_of_a_large_scan(real_scans, scan):
    """Two independent halves of a real scan (100k and 25k points each), the second moved and
    noisy: the matcher gets the check's 8,000-point subsets, on a voxel of THINNED_FEATURE_SPACINGS
    spacings (the default 1.5 left it 65 and 11 deg off here)."""
    from service import registration

    rng = np.random.default_rng(0)
    cloud = real_scans[scan]
    source, target = (cloud[rng.random(len(cloud)) < 0.5] for _ in range(2))
    target = apply_transform(target + rng.normal(0.0, 0.002, target.shape), TRUE_ROTATION, TRUE_TRANSLATION)
    options, settings, _ = pipeline_inputs(None, None, method="auto")
    prepared = registration._prepare(source, target, STARTS_POINTS, options, settings)
    assert len(prepared.check.source) < len(prepared.source)  # thinned
    guess = registration._feature_guess(prepared)
    assert rotation_angle_deg(guess.rotation, TRUE_ROTATION) < 2.0


@pytest.mark.parametrize("method", ["auto", "global"])
@pytest.mark.parametrize("wider_points", [20_000, 0], ids=["wider", "once"])
def test_feature_matching_lost_on_the_checks_subset_matches_again_on_more_points(
    real_scans, monkeypatch, wider_points, method
):
    """Under `auto` and `global`, where feature matching's answer on the check's subset of a large scan
    fails the check, it matches once more on up to WIDER_FEATURE_POINTS of each cloud (a stand-in here,
    lost on the subset and right on more points), and that answer, verified, is the request's."""
    from service import registration

    monkeypatch.setattr(registration, "WIDER_FEATURE_POINTS", wider_points)
    matched = []

    def stand_in(source, target, spacing, spacings):
        matched.append(len(source))
        lost = len(source) <= registration.CHECK_MAX_POINTS
        return (euler_to_matrix([90.0, 0.0, 0.0]) if lost else TRUE_ROTATION), TRUE_TRANSLATION

    monkeypatch.setattr(registration, "feature_match", stand_in)
    source = real_scans["kitti_000008_fov"]
    target = apply_transform(source, TRUE_ROTATION, TRUE_TRANSLATION)
    options, settings, _ = pipeline_inputs(None, None, method=method)
    turn = euler_to_matrix([0.0, 90.0, 0.0])  # every draft and model answer far from the truth
    draft = Network("object", 384, recording([], "draft", turn), "draft")
    networks = [Network("object", 768, recording([], "model", turn), draft=draft)]
    result = asyncio.run(register_clouds(source, target, options, settings, networks))
    subset_size = registration.CHECK_MAX_POINTS
    if wider_points:
        assert matched == [subset_size, min(len(source), wider_points)]
        assert (result.stage, result.verified) == ("features", True)
        assert rotation_angle_deg(result.rotation, TRUE_ROTATION) < 0.01
    else:
        assert matched == [subset_size]
        assert not (result.verified and rotation_angle_deg(result.rotation, TRUE_ROTATION) < 2.0)


@pytest.mark.parametrize("lost", [True, False], ids=["lost on the subset", "unpinned on the subset"])
def test_feature_matching_unpinned_on_more_points_or_on_the_subset_ends_the_search(monkeypatch, lost):
    """Two views of a table top. Where the match on the check's subset is lost (its answer fits nothing)
    and the one on more points is right but unpinned, the second answer is feature matching's; where
    the subset's match is already right and unpinned, no second match is made. Either fits and
    settles, so it ends the search (no model, no rotated start) and is given, flagged."""
    from service import registration

    truth = TABLE_VIEWS_TURN
    matched = []

    def stand_in(source, target, spacing, spacings):
        matched.append(len(source))
        subset = len(source) <= registration.CHECK_MAX_POINTS
        return (euler_to_matrix([0.0, 0.0, 90.0]) @ truth if lost and subset else truth), np.zeros(3)

    result, asked, source = table_views_answer(monkeypatch, stand_in)
    wider = [min(len(source), registration.WIDER_FEATURE_POINTS)] if lost else []
    assert matched == [registration.CHECK_MAX_POINTS, *wider]
    assert (result.stage, result.verified) == ("features", False) and "pin" in result.reason
    assert rotation_angle_deg(result.rotation, truth) < 0.5 and ("model", 768) not in asked


def test_feature_matching_that_agrees_with_a_verified_answer_is_not_refined_again(real_scans, monkeypatch):
    """Its guess within AGREEMENT_DEG of the verified answer confirms it as it is; a guess further off
    is refined and checked (here it then fits too poorly to contradict the answer)."""
    from service import registration

    checked, check = [], registration._checked
    monkeypatch.setattr(registration, "_checked", lambda *args: checked.append(args[1]) or check(*args))
    source = real_scans["kitti_000008_fov"]
    target = apply_transform(source, TRUE_ROTATION, TRUE_TRANSLATION)
    agreeing = register(source, target, 768, recording([], "model"), method="auto")  # the starts' clouds: subsets
    assert agreeing.verified and agreeing.stage == "ifnet" and len(checked) == 1
    checked.clear()
    turned = euler_to_matrix([90.0, 0.0, 0.0]) @ TRUE_ROTATION
    monkeypatch.setattr(registration, "feature_match", lambda *args: (turned, TRUE_TRANSLATION))
    disagreeing = register(source, target, 768, recording([], "model"), method="auto")
    assert disagreeing.verified and disagreeing.stage == "ifnet" and len(checked) == 2
    assert rotation_angle_deg(checked[1], turned) == pytest.approx(0.0, abs=1e-9)  # the guess, refined and checked


@pytest.mark.parametrize("method", ["ifnet", "auto"])
def test_a_pairs_clouds_are_made_ready_for_refinement_once(real_scans, monkeypatch, method):
    """Fine refinement and the check (and under auto, feature matching's refinement and check)
    share one set of normals and covariances per cloud, and every coarse pass another, on fewer
    points: four estimates per request, the coarse pass's clouds being subsets of the check's."""
    import small_gicp

    from service import registration

    estimates, estimate = [], small_gicp.estimate_normals_covariances

    def counted(*args, **kwargs):
        estimates.append(len(args[0].points()))
        return estimate(*args, **kwargs)

    monkeypatch.setattr(small_gicp, "estimate_normals_covariances", counted)
    source = real_scans["kitti_000008_fov"]
    noise = np.random.default_rng(0).normal(scale=1e-4 * radius(source), size=source.shape)  # work for refinement
    target = apply_transform(source, TRUE_ROTATION, TRUE_TRANSLATION) + noise
    result = register(source, target, 768, recording([], "model"), method=method, refine=RefineOptions())
    assert result.verified and result.refinement.iterations >= 1
    checked = min(len(source), registration.CHECK_MAX_POINTS)  # 17k points: a subset
    coarse = registration.COARSE_POINTS
    assert estimates == [checked, checked, coarse, coarse]  # the target's, then the source's


def test_the_coarse_pass_refines_fewer_points_of_large_clouds(real_scans, monkeypatch):
    """Past 2 x COARSE_POINTS per cloud the coarse pass runs on COARSE_POINTS of each, the fine pass
    and the check on the check's clouds; smaller clouds run both passes on the check's."""
    from model.geometry import AlignmentClouds
    from service import registration

    refined, refine = [], AlignmentClouds.refine

    def recorded(clouds, *args, **kwargs):
        refined.append(len(clouds.source))
        return refine(clouds, *args, **kwargs)

    monkeypatch.setattr(AlignmentClouds, "refine", recorded)
    large = real_scans["kitti_000008_fov"]  # 17k points
    for source in (large, subset(large, 2 * registration.COARSE_POINTS)):
        refined.clear()
        target = apply_transform(source, TRUE_ROTATION, TRUE_TRANSLATION)
        result = register(source, target, 768, recording([], "model"), method="ifnet", refine=RefineOptions())
        assert result.verified
        checked = min(len(source), registration.CHECK_MAX_POINTS)
        coarse = registration.COARSE_POINTS if len(source) > 2 * registration.COARSE_POINTS else checked
        assert refined[:2] == [coarse, checked]


def test_farthest_point_sampling_picks_the_point_farthest_from_those_chosen():
    points = np.random.default_rng(7).normal(size=(500, 3)) * [3.0, 1.0, 0.2] + 10.0  # anisotropic, off-centre
    chosen = farthest_point_sample(points, 60, start=4)
    assert chosen[0] == 4 and len(set(chosen.tolist())) == 60
    for i in range(1, 60):
        nearest_chosen = ((points[:, None, :] - points[chosen[:i]][None]) ** 2).sum(-1).min(axis=1)
        assert chosen[i] == np.argmax(nearest_chosen)


def sample_indices(cloud, count, sampling, seed, fps_max_input):
    return CloudSampler(cloud, sampling, seed, fps_max_input).indices(count)


def test_sampling_is_reproducible_and_per_cloud(real_scans):
    cloud = real_scans["kitti_000008_fov"]
    for sampling in ("fps", "random"):
        first = sample_indices(cloud, 256, sampling, seed=5, fps_max_input=4096)
        again = sample_indices(cloud, 256, sampling, seed=5, fps_max_input=4096)
        np.testing.assert_array_equal(first, again)
        assert len(np.unique(first)) == 256
    assert not np.array_equal(
        sample_indices(cloud, 256, "random", 5, 4096), sample_indices(cloud, 256, "random", 6, 4096)
    )
    for sampling in ("fps", "random"):  # a cloud of the network's size is kept as it is, in its order
        np.testing.assert_array_equal(sample_indices(cloud[:256], 256, sampling, 5, 4096), np.arange(256))
    small = sample_indices(cloud[:100], 256, "fps", seed=0, fps_max_input=4096)
    assert len(small) == 256 and set(small.tolist()) == set(range(100))  # every point kept, some repeated


def test_a_second_count_gets_what_it_would_get_first(real_scans):
    """One sampler serves a request's point counts: extending farthest points, or drawing afresh."""
    cloud = real_scans["kitti_000008_fov"]
    for sampling, cap, small in (("fps", 4096, 128), ("fps", 100_000, 128), ("random", 4096, 128), ("fps", 4096, 8192)):
        sampler = CloudSampler(cloud, sampling, 5, cap)
        first = sampler.indices(small)
        for count in (384, small):
            np.testing.assert_array_equal(sampler.indices(count), sample_indices(cloud, count, sampling, 5, cap))
        np.testing.assert_array_equal(sampler.indices(small), first)
    farthest = CloudSampler(cloud, "fps", 5, 4096)
    np.testing.assert_array_equal(farthest.indices(384)[:128], farthest.indices(128))


def test_non_finite_model_output_is_reported(real_scans):
    source = real_scans["pcl_bunny_view0"]

    async def broken(source_n, target_n):
        return Prediction(np.full((3, 3), np.nan), np.zeros(3))

    with pytest.raises(RegistrationFailed, match="non-finite"):
        register(source, source, 64, predict=broken)


# ---------------------------------------------------------------- input checks


def cloud(count: int = 100, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(count, 3))


@pytest.mark.parametrize(
    ("value", "message"),
    [
        ([[1.0, 2.0, 3.0], [4.0, 5.0]], "point 1 has 2 coordinates"),
        ([[1.0, 2.0, 3.0, 4.0]], r"N x 3\), got shape \[1, 4\]"),
        ([[1.0, "a", 3.0]], "non-numeric coordinate 'a'"),
        ([[1.0, None, 3.0]], "non-numeric coordinate None"),
        ([], "is empty"),
        ([1.0, 2.0, 3.0], "point 0 must be a list"),
        ("1 2 3", "must be a list of"),
        ([[0.0, float("nan"), 1.0], [0.0, 0.0, float("inf")]], r"2 point\(s\) have NaN or infinite.*index 0"),
        (np.zeros((5, 2)), r"got shape \[5, 2\]"),
    ],
)
def test_as_points_names_the_problem(value, message):
    with pytest.raises(InvalidInput, match=message) as caught:
        as_points(value, "source")
    assert caught.value.field == "source"


def test_as_points_accepts_integers_and_arrays():
    assert as_points([[1, 2, 3], [4, 5, 6]], "target").dtype == np.float64
    assert as_points(np.ones((4, 3), np.float32), "target").shape == (4, 3)


@pytest.mark.parametrize(
    ("points", "message"),
    [
        (np.ones((50, 3)), "all points are identical"),
        (np.outer(np.arange(50.0), [1.0, 2.0, 3.0]) + 7.0, "all points lie on one line"),
        (
            np.concatenate([cloud(49), [[1e9, 0.0, 0.0]]]),
            r"or a few lie so far from the rest that they look so: remove them",
        ),
        (cloud(50) * 0.01 + 5e11, r"coincide to within the rounding of coordinates up to 5e\+11 \(shift it nearer"),
        (cloud(10), "has 10 points; at least 32"),
        (np.repeat(cloud(10), 5, axis=0), r"only 10 distinct points \(40 exact duplicates\)"),
        (cloud(600), "more than the limit of 500"),
    ],
)
def test_clouds_that_cannot_be_registered(points, message):
    with pytest.raises(InvalidInput, match=message) as caught:
        register(points, cloud(100), 64, min_points=32, max_cloud_points=500)
    assert caught.value.field == "source"


def test_a_planar_cloud_is_accepted():
    plane = np.c_[cloud(100)[:, :2], np.zeros(100)]
    assert degeneracy(plane) is None
    assert register(plane, plane, 64).fitness == 1.0


def test_init_must_be_a_rigid_transform():
    assert as_rigid_transform(np.round(INIT, 5)).shape == (4, 4)  # a few printed decimals are fine
    rotation, _ = from_matrix(as_rigid_transform(np.round(INIT, 5)))
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    scaled = INIT.copy()
    scaled[:3, :3] *= 2.0
    mirrored = INIT @ np.diag([1.0, 1.0, -1.0, 1.0])
    bad_last_row = INIT.copy()
    bad_last_row[3] = [0.0, 0.0, 1.0, 1.0]
    for matrix, message in [
        (scaled, "not a rigid transform"),
        (mirrored, "not a rigid transform"),
        (bad_last_row, "not a rigid transform"),
        (np.eye(3), r"4x4 matrix, got shape \[3, 3\]"),
        (np.full((4, 4), np.nan), "NaN or infinite"),
        ([[1, 2], [3]], "4x4 matrix of numbers"),
    ]:
        with pytest.raises(InvalidInput, match=message) as caught:
            as_rigid_transform(matrix)
        assert caught.value.field == "init"


def test_upsampled_only_when_a_cloud_has_fewer_distinct_points_than_the_network_takes():
    cloud = np.random.default_rng(3).normal(size=(64, 3))

    async def identity(source: np.ndarray, target: np.ndarray) -> Prediction:
        return Prediction(np.eye(3), np.zeros(3))

    exact = register(cloud, cloud, 64, identity, min_points=8)
    short = register(cloud[:63], cloud, 64, identity, min_points=8)
    assert (exact.points.source.upsampled, exact.points.source.network_points) == (False, 64)
    assert (short.points.source.upsampled, short.points.source.network_points) == (True, 64)
    assert short.points.target.upsampled is False


def test_a_second_point_count_reuses_the_pairs_checked_points(monkeypatch):
    """A model of another point count gets the pair made ready as from scratch, without checking
    the clouds for duplicates again or building the check's clouds twice."""
    import service.registration as registration

    rng = np.random.default_rng(5)
    source = np.vstack([rng.normal(size=(400, 3)), np.zeros((3, 3))])  # with duplicates
    target = rng.normal(size=(500, 3))
    options, settings, _ = pipeline_inputs(64, None)
    first = registration._prepare(source, target, 64, options, settings)
    fresh = registration._prepare(source, target, 32, options, settings)
    checked = []
    monkeypatch.setattr(registration, "check_cloud", lambda *args: checked.append(args) or args[0])
    second = registration._prepare(source, target, 32, options, settings, base=first)
    assert checked == [] and second.check is first.check and second.source is first.source
    np.testing.assert_array_equal(second.source_network, fresh.source_network)
    np.testing.assert_array_equal(second.target_network, fresh.target_network)
    assert second.points == fresh.points


def test_global_does_not_verify_a_pose_that_a_symmetric_shape_fits_twice(monkeypatch):
    """Under `global` the rotated starts judge feature matching's answer: on a box, the pose turned
    half a turn about one of its axes fits as well as the right one, so neither is verified."""
    from service import registration

    rng = np.random.default_rng(0)
    half = np.array([0.5, 0.3, 0.15])
    points = rng.uniform(-1.0, 1.0, (96, 3)) * half
    face = rng.integers(0, 3, 96)
    points[np.arange(96), face] = np.sign(points[np.arange(96), face]) * half[face]  # on the surface
    halfturns = [np.diag(signs) for signs in ([1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1])]
    source = np.concatenate([points @ turn.T for turn in halfturns])  # the box's own symmetries
    target = apply_transform(source, TRUE_ROTATION, TRUE_TRANSLATION)
    flipped = TRUE_ROTATION @ halfturns[1]
    monkeypatch.setattr(registration, "feature_match", lambda *args: (flipped, TRUE_TRANSLATION))
    answer = register(source, target, 384, method="global", refine={})
    assert answer.stage in ("features", "multistart") and not answer.verified
    assert answer.reason.startswith("ambiguous")


def test_a_verified_draft_answer_feature_matching_does_not_confirm_stays_a_candidate(real_scans, monkeypatch):
    """Feature matching's guess lies 25 deg and 50 m off, so the draft's verified answer does not
    stand; the model's answer and every later draft call (the rotated starts) are spoiled. The
    draft's answer is not thrown away: judged with the other answers, it is the answer, verified."""
    from service import registration

    guess = euler_to_matrix([25.0, 0.0, 0.0]) @ TRUE_ROTATION, TRUE_TRANSLATION + 50.0
    monkeypatch.setattr(registration, "feature_match", lambda *args: guess)
    asked = []
    right_once = recording(asked, "draft")

    async def draft_call(source_n, target_n):
        if not asked:
            return await right_once(source_n, target_n)
        asked.append(("draft", len(source_n)))
        return Prediction(np.eye(3), np.zeros(3))

    spoiled = recording(asked, "model", turn=euler_to_matrix([0.0, 60.0, 0.0]))
    networks = [Network("object", 768, spoiled, draft=Network("object", 384, draft_call, "draft"))]
    options, settings, _ = pipeline_inputs(None, None, method="auto")
    source = real_scans["kitti_000008_fov"]
    target = apply_transform(source, TRUE_ROTATION, TRUE_TRANSLATION)
    result = asyncio.run(register_clouds(source, target, options, settings, networks))
    assert ("model", 768) in asked  # the draft's answer did not stand
    assert (result.stage, result.verified) == ("draft", True), result.reason
    assert rotation_angle_deg(result.rotation, TRUE_ROTATION) < 0.01
