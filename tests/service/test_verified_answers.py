"""Right or flagged: every answer says whether it passed the check (`verified`, `reason`) and
which stage gave it; `auto` falls back to the global search, which handles any rotation."""

import dataclasses
import io
from pathlib import Path

import numpy as np
import pytest

from model.geometry import (
    apply_transform,
    euler_to_matrix,
    extent,
    from_matrix,
    principal_axes,
    rotation_angle_deg,
    slides,
)
from service.formats import read_cloud_file
from service.settings import Settings

pytestmark = pytest.mark.anyio

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
TRUTH = np.loadtxt(EXAMPLES / "true_transform.txt")
TURN = euler_to_matrix([150.0, 40.0, -70.0])  # far outside the network's 45 degrees per axis


def sample_pair(turned: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The shipped sample pair, its source optionally turned first: (source, target, true 4x4)."""
    source = read_cloud_file(EXAMPLES / "source.ply")
    target = read_cloud_file(EXAMPLES / "target.pcd")
    if not turned:
        return source, target, TRUTH
    turned_source = apply_transform(source, TURN, np.zeros(3))
    undo = np.eye(4)
    undo[:3, :3] = TURN.T
    return turned_source, target, TRUTH @ undo


def npz(source: np.ndarray, target: np.ndarray) -> bytes:
    archive = io.BytesIO()
    np.savez(archive, source=source, target=target)
    return archive.getvalue()


async def register(client, source, target, **options) -> dict:
    import json

    answer = await client.post(
        "/register",
        content=npz(source, target),
        headers={"Content-Type": "application/x-npz"},
        params={"options": json.dumps(options)},
    )
    assert answer.status_code == 200, answer.text
    return answer.json()


def rotation_error(answer: dict, truth: np.ndarray) -> float:
    return float(rotation_angle_deg(from_matrix(np.asarray(answer["transform"]))[0], truth[:3, :3]))


async def test_a_right_answer_is_verified(serve, shipped_model):
    source, target, truth = sample_pair(turned=False)
    async with serve(Settings(model_path=shipped_model, warmup=False)) as (_, client):
        answer = await register(client, source, target, method="ifnet", refine=True)
    assert rotation_error(answer, truth) < 0.5
    assert answer["verified"] is True and answer["reason"] is None and answer["stage"] == "ifnet"
    assert answer["fitness"] > 0.5 and answer["fitness_threshold"] > 0


async def test_clouds_in_map_coordinates_are_registered(serve, shipped_model):
    """The sample pair moved three million units out (as LiDAR scans in map coordinates are): feature
    matching's voxel keys overflowed there and crashed the process, and refinement lost precision
    (the check failed it). Out there feature matching's guess, on a voxel grid placed otherwise, is
    99 deg off and vouches for nothing, so the rotated starts judge the answer harder: poses 7 and
    180 deg from it also pass the check, which may flag it as ambiguous."""
    source, target, truth = sample_pair(turned=False)
    offset = np.array([3e6, -2e6, 1e6])
    async with serve(Settings(model_path=shipped_model, warmup=False)) as (_, client):
        answer = await register(client, source + offset, target + offset, method="auto", refine=True)
    assert rotation_error(answer, truth) < 0.5
    assert answer["verified"] is True or answer["reason"].startswith("ambiguous"), answer["reason"]
    # Each source point lands where the true motion puts it (about the far origin, a tiny turn
    # error moves the translation a lot, but not the points).
    landed = apply_transform(source + offset, *from_matrix(np.asarray(answer["transform"])))
    assert np.linalg.norm(landed - apply_transform(source, *from_matrix(truth)) - offset, axis=1).max() < 0.02


async def test_a_scan_in_a_sensors_frame_registers_onto_one_in_a_maps(serve, shipped_model):
    """The sample pair's target moved three million units out, its source left near the origin:
    feature matching moved both by the target's centre, which left the source out of its keys'
    reach, and the crash took the request with it (the connection closed without an answer)."""
    source, target, truth = sample_pair(turned=False)
    offset = np.array([3e6, -2e6, 1e6])
    async with serve(Settings(model_path=shipped_model, warmup=False)) as (_, client):
        answer = await register(client, source, target + offset, method="auto", refine=True)
    assert rotation_error(answer, truth) < 0.5
    assert answer["verified"] is True or answer["reason"].startswith("ambiguous"), answer["reason"]
    landed = apply_transform(source, *from_matrix(np.asarray(answer["transform"])))
    assert np.linalg.norm(landed - apply_transform(source, *from_matrix(truth)) - offset, axis=1).max() < 0.02


@pytest.mark.slow
async def test_auto_finds_a_large_rotation_the_network_alone_gets_wrong(serve, shipped_model):
    """The sample pair turned 150 deg: the rotated starts find it. The table fits a pose 18 deg off
    well enough for the check to pass it (fitness 0.49 against 0.81), so the answer is flagged."""
    source, target, truth = sample_pair(turned=True)
    async with serve(Settings(model_path=shipped_model, warmup=False)) as (_, client):
        network = await register(client, source, target, method="ifnet", refine=True)
        auto = await register(client, source, target, method="auto")
        metrics = (await client.get("/metrics")).text
    assert rotation_error(network, truth) > 10 and network["verified"] is False and network["reason"]
    assert rotation_error(auto, truth) < 1.0, auto
    assert auto["verified"] is False and auto["reason"].startswith("ambiguous")
    assert auto["stage"] in ("multistart", "features")  # feature matching may find it too, not deterministically
    assert 'ifnet_answers_total{model="object",stage="ifnet",verified="false"} 1.0' in metrics
    assert f'ifnet_answers_total{{model="object",stage="{auto["stage"]}",verified="false"}} 1.0' in metrics


@pytest.mark.slow
async def test_clouds_with_nothing_in_common_get_a_flagged_answer_not_an_error(serve, shipped_model):
    rng = np.random.default_rng(4)
    source, target = rng.normal(size=(500, 3)), rng.uniform(-1.0, 1.0, size=(500, 3)) * [3.0, 0.2, 0.2]
    async with serve(Settings(model_path=shipped_model, warmup=False)) as (_, client):
        answer = await register(client, source, target, method="global")
    assert answer["verified"] is False and answer["reason"]
    assert answer["stage"] in ("multistart", "features")


@pytest.mark.parametrize("method", ["best", "", 1, None])
async def test_unknown_methods_are_refused_naming_the_field(serve, tiny_model, method):
    async with serve(Settings(model_path=tiny_model, warmup=False)) as (_, client):
        answer = await client.post(
            "/register", json={"source": [[0, 0, 0]] * 3, "target": [[0, 0, 0]] * 3, "method": method}
        )
    if method is None:  # null is the service's default method
        assert answer.status_code == 422 and answer.json()["errors"][0]["field"] == "source"
        return
    assert answer.status_code == 422
    assert answer.json()["errors"][0]["field"] == "method"


def box_surface(count: int, rng: np.random.Generator) -> np.ndarray:
    """Points on the surface of a 4 x 2 x 1 box centred on the origin: it fits itself turned 180
    degrees about any of its axes."""
    half = np.array([2.0, 1.0, 0.5])
    points = rng.uniform(-1.0, 1.0, size=(count, 3)) * half
    axis = rng.integers(0, 3, size=count)
    points[np.arange(count), axis] = rng.choice([-1.0, 1.0], size=count) * half[axis]
    return points


def symmetric_box(count: int, rng: np.random.Generator) -> np.ndarray:
    """box_surface points and each one's twin half a turn about the box's short axis: that turn fits
    exactly as well as no turn, whatever the inlier distance."""
    points = box_surface(count // 2, rng)
    return np.concatenate([points, points * [-1.0, -1.0, 1.0]])


def test_an_answer_another_answer_contradicts_is_not_verified():
    """The "network" answers the box turned 180 degrees, a fit as good as the true motion's, which
    feature matching finds: two verified answers contradict each other, so neither is verified."""
    import asyncio

    from conftest import pipeline_inputs

    from service.batcher import Prediction
    from service.registration import register_clouds

    rng = np.random.default_rng(5)
    rotation = euler_to_matrix([20.0, 10.0, 5.0])
    source = box_surface(3000, rng)
    target = source @ rotation.T
    flip = rotation @ np.diag([-1.0, -1.0, 1.0]) @ rotation.T  # half a turn about the box's own short axis

    async def flipped(source_n, target_n):
        return Prediction(flip @ rotation, np.zeros(3))  # each cloud is centred on its centroid, the box's centre

    answer = asyncio.run(register_clouds(source, target, *pipeline_inputs(768, flipped, refine={}, method="ifnet")))
    assert answer.verified is False and answer.reason.startswith("ambiguous"), answer.reason
    assert answer.stage in ("ifnet", "features")  # whichever fits best, flagged


def test_every_rotated_start_the_global_path_keeps_can_be_the_answer():
    """Whichever refined start wins, its timings make a valid response (a later start once lacked
    the preprocessing time and its answer failed the response schema)."""
    from conftest import pipeline_inputs

    from service.batcher import Prediction
    from service.registration import _finish_multistart, _prepare
    from service.schemas import ModelDescription, RegisterResponse

    rng = np.random.default_rng(6)
    source = box_surface(1500, rng)
    options, settings, _ = pipeline_inputs(256, None, refine={}, method="global")
    prepared = _prepare(source, source @ euler_to_matrix([30.0, 0.0, 0.0]).T, 256, options, settings)
    predictions = [Prediction(np.eye(3), np.zeros(3), inference_ms=5.0) for _ in range(24)]
    results, cost = _finish_multistart(prepared, predictions, "object", options)
    assert len(results) > 1 and cost["inference_ms"] == 120.0
    model = ModelDescription.model_construct()
    for result in results:
        assert result.timings_ms.keys() == results[0].timings_ms.keys()
        RegisterResponse.from_result(result, model, read_ms=1.0, total_ms=2.0)


def box_answer():
    """A multistart answer on a box, to vary: the fields of a result any stage could give."""
    from conftest import pipeline_inputs

    from service.batcher import Prediction
    from service.registration import _finish_multistart, _prepare

    source = box_surface(1500, np.random.default_rng(7))
    options, settings, _ = pipeline_inputs(256, None, refine={}, method="global")
    prepared = _prepare(source, source, 256, options, settings)
    return _finish_multistart(prepared, [Prediction(np.eye(3), np.zeros(3))] * 24, "object", options)[0][0]


def fitted(result, **changes):
    """The result with `changes`; a fitness or inlier_rmse among them is the check's own too (as
    without a fitness_threshold of the request's), which answers are judged by."""
    score = {name: changes[name] for name in ("fitness", "inlier_rmse") if name in changes}
    return dataclasses.replace(result, **changes, score=result.score._replace(**score))


def test_an_unverified_answer_that_fits_as_well_also_contradicts():
    """A near-symmetric shape: one answer slides (unverified), another 30 degrees away passes the
    check; the two fit about as well, so the second is not verified either. A poorer fit does not
    contradict."""
    from service.registration import _unless_contradicted

    result = box_answer()
    answer = fitted(result, rotation=np.eye(3), verified=True, reason=None, fitness=0.72)
    turned = euler_to_matrix([30.0, 0.0, 0.0])
    sliding = fitted(result, rotation=turned, verified=False, reason="slides", fitness=0.70)
    poorer = fitted(sliding, fitness=0.40)

    flagged = _unless_contradicted(answer, [answer, sliding])
    assert flagged.verified is False and flagged.reason.startswith("ambiguous")
    assert _unless_contradicted(answer, [answer, poorer]).verified is True


def test_a_contradicted_answer_gives_way_to_the_best_fitting_one():
    """A start verified at fitness 0.725 and the network's unverified answer 30 degrees away at
    0.934 (a shape the check cannot pin down): nothing stands verified, so `auto` gives the better
    fitting answer, flagged; `ifnet` gives the network's answer whatever else fits."""
    from service.registration import _given

    result = box_answer()
    turned = euler_to_matrix([30.0, 0.0, 0.0])
    network = fitted(result, rotation=turned, verified=False, reason="slides", fitness=0.934, stage="ifnet")
    start = fitted(result, rotation=np.eye(3), verified=True, reason=None, fitness=0.725)

    given = _given([network, start], "auto")
    assert (given.stage, given.fitness, given.verified) == ("ifnet", 0.934, False)
    assert given.reason.startswith("ambiguous")
    network_answer = _given([network, start], "ifnet")
    assert (network_answer.stage, network_answer.verified, network_answer.reason) == ("ifnet", False, "slides")


def test_the_rotated_starts_judge_a_verified_answer(monkeypatch):
    """The model and feature matching agree on a symmetric box turned 180 deg, which passes the
    check. The rotated starts, judging it, find the true motion, which passes too: the clouds do not
    tell the two apart, so the answer (either, as they fit alike) is flagged."""
    import asyncio

    from conftest import kabsch, pipeline_inputs

    from service import registration
    from service.batcher import Prediction

    rng = np.random.default_rng(5)
    rotation = euler_to_matrix([20.0, 10.0, 5.0])
    source = symmetric_box(3000, rng)
    flip = rotation @ np.diag([-1.0, -1.0, 1.0]) @ rotation.T  # half a turn about the box's own short axis
    monkeypatch.setattr(registration, "feature_match", lambda *args: (flip @ rotation, np.zeros(3)))

    async def flipped_at_full_size(source_n, target_n):
        if len(source_n) == registration.STARTS_POINTS:  # a start: the true motion (the points correspond)
            return Prediction(*kabsch(source_n.astype(np.float64), target_n.astype(np.float64)))
        return Prediction(flip @ rotation, np.zeros(3))

    options = pipeline_inputs(768, flipped_at_full_size, refine={}, method="auto")
    answer = asyncio.run(registration.register_clouds(source, source @ rotation.T, *options))
    assert answer.verified is False and answer.reason.startswith("ambiguous"), answer.reason
    assert min(rotation_angle_deg(answer.rotation, turn) for turn in (rotation, flip @ rotation)) < 0.01


def test_a_verified_rival_that_fits_worse_with_looser_inliers_does_not_contradict():
    """A wrong pose can pass the check on chance inliers, spread across the inlier distance; a right
    answer's lie near the surfaces. A verified rival that fits no better, with inlier residuals 1.25x
    the answer's or more, does not contradict it; one about as tight does."""
    from service.registration import _unless_contradicted

    result = box_answer()
    answer = fitted(result, rotation=np.eye(3), verified=True, reason=None, fitness=0.95, inlier_rmse=0.2)
    flip = euler_to_matrix([180.0, 0.0, 0.0])
    loose = fitted(answer, rotation=flip, fitness=0.6, inlier_rmse=0.5)
    as_tight = fitted(loose, inlier_rmse=0.22)
    fitting_better = fitted(loose, fitness=0.96)

    assert _unless_contradicted(answer, [answer, loose]).verified is True
    for rival in (as_tight, fitting_better):
        flagged = _unless_contradicted(answer, [answer, rival])
        assert flagged.verified is False and flagged.reason.startswith("ambiguous")


def test_a_poorer_verified_fit_beside_the_answer_contradicts_it():
    """A second pose 9 deg from the answer passing the check, fitting clearly worse (0.66 against
    0.77) with inliers as tight: the clouds pin the pose down no better than that, so the answer is
    not verified (on a jittered ModelNet40 shape under any rotation the answer itself was 2.0 deg and
    2.4 % of the extent off). A verified pose within AGREEMENT_DEG agrees with it."""
    from service.registration import AGREEMENT_DEG, _unless_contradicted

    result = box_answer()
    answer = fitted(result, rotation=np.eye(3), verified=True, reason=None, fitness=0.77, inlier_rmse=0.2)
    beside = fitted(answer, rotation=euler_to_matrix([9.0, 0.0, 0.0]), fitness=0.66, inlier_rmse=0.2)
    agreeing = fitted(beside, rotation=euler_to_matrix([AGREEMENT_DEG - 1.0, 0.0, 0.0]))

    flagged = _unless_contradicted(answer, [answer, beside])
    assert flagged.verified is False and flagged.reason.startswith("ambiguous")
    assert _unless_contradicted(answer, [answer, agreeing]).verified is True


def box_with_a_block() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A box with a block on one face, its true turn (150 deg, beyond the draft's reach) and that
    turn after half a turn about the box's short axis: a flipped pose that fits all but the block."""
    rng = np.random.default_rng(8)
    block = rng.uniform([1.7, 0.7, 0.5], [2.0, 1.0, 0.6], size=(100, 3))  # on the top face, at a corner
    truth = euler_to_matrix([150.0, 40.0, -70.0])
    return np.concatenate([box_surface(3000, rng), block]), truth, truth @ np.diag([-1.0, -1.0, 1.0])


def test_a_draft_answer_at_feature_matchings_turn_is_judged_by_its_half_turns(monkeypatch):
    """A box with a block on one face, turned 150 deg, beyond the draft's reach. Feature matching
    lands on the box turned half a turn from the truth (the block aside, it fits), and so does the
    draft asked from there: verified and confirmed. Its half turns about the target's principal axes
    find the truth, which fits better with tighter inliers: it is the answer, verified. Matching
    under 0.85 of the source, the flipped answer is judged by the rotated starts too (the draft at
    every start, stuck here). The model is never asked."""
    import asyncio

    from conftest import pipeline_inputs

    from service import registration
    from service.batcher import Prediction
    from service.registration import Network

    source, truth, flipped = box_with_a_block()
    monkeypatch.setattr(registration, "feature_match", lambda *args: (flipped, np.zeros(3)))
    asked = []

    async def stuck(source_n, target_n):  # answers "no turn": far from the guess, then the guess itself
        asked.append(len(source_n))
        return Prediction(np.eye(3), np.zeros(3))

    options, settings, _ = pipeline_inputs(None, None, method="auto", refine={})
    networks = [Network("object", 768, stuck, draft=Network("object", 384, stuck, "draft"))]
    answer = asyncio.run(registration.register_clouds(source, source @ truth.T, options, settings, networks))
    assert asked == [384, 384] + [registration.STARTS_POINTS] * len(registration.STARTS)
    assert (answer.stage, answer.verified) == ("multistart", True), answer.reason
    assert rotation_angle_deg(answer.rotation, truth) < 0.01


def test_a_draft_answer_beyond_its_reach_is_judged_by_its_half_turns_though_asked_as_the_source_lies(monkeypatch):
    """The same box: the draft, asked for the source as it lies, answers the flipped pose, beyond
    the 45 deg it knows, and feature matching agrees. Two methods agreeing do not rule out a flip
    (on a ModelNet10 shape under any rotation both landed on one, 179.8 deg off): its half turns
    judge it and find the truth, the answer."""
    import asyncio

    from conftest import pipeline_inputs

    from service import registration
    from service.batcher import Prediction
    from service.registration import Network

    source, truth, flipped = box_with_a_block()
    monkeypatch.setattr(registration, "feature_match", lambda *args: (flipped, np.zeros(3)))
    asked = []

    async def flips_first(source_n, target_n):  # the flip as the source lies; stuck at every start after
        asked.append(len(source_n))
        return Prediction(flipped if len(asked) == 1 else np.eye(3), np.zeros(3))

    options, settings, _ = pipeline_inputs(None, None, method="auto", refine={})
    networks = [Network("object", 768, flips_first, draft=Network("object", 384, flips_first, "draft"))]
    answer = asyncio.run(registration.register_clouds(source, source @ truth.T, options, settings, networks))
    assert asked[0] == 384 and 768 not in asked  # confirmed, the draft's answer from the first call stands
    assert (answer.stage, answer.verified) == ("multistart", True), answer.reason
    assert rotation_angle_deg(answer.rotation, truth) < 0.01


def test_a_draft_answer_at_the_users_init_is_judged_by_its_half_turns(monkeypatch):
    """The same box, the request's `init` at its flipped pose: the draft stays there (within its
    reach of `init`) and feature matching agrees. Its half turns still find the truth (the rotated
    starts judge it too, but with this network stuck at every start none lands on the truth)."""
    import asyncio

    from conftest import pipeline_inputs

    from model.geometry import to_matrix
    from service import registration
    from service.batcher import Prediction
    from service.registration import Network

    source, truth, flipped = box_with_a_block()
    monkeypatch.setattr(registration, "feature_match", lambda *args: (flipped, np.zeros(3)))

    async def stays(source_n, target_n):
        return Prediction(np.eye(3), np.zeros(3))

    init = to_matrix(flipped, np.zeros(3)).tolist()
    options, settings, _ = pipeline_inputs(None, None, method="auto", refine={}, init=init)
    networks = [Network("object", 768, stays, draft=Network("object", 384, stays, "draft"))]
    answer = asyncio.run(registration.register_clouds(source, source @ truth.T, options, settings, networks))
    assert (answer.stage, answer.verified) == ("multistart", True), answer.reason
    assert rotation_angle_deg(answer.rotation, truth) < 0.01


def test_a_draft_answer_at_the_users_init_matching_little_is_judged_by_the_rotated_starts(monkeypatch):
    """A pinwheel of three bars with a marker on one: a third of a turn about its axis fits all but
    the marker. The request's `init` is that turn; the draft, knowing only turns up to 45 deg, stays
    there and feature matching agrees: verified, matching 0.69 of the source. No half turn is a third
    of a turn; the rotated starts find the truth, which fits in full and is the answer."""
    import asyncio

    from conftest import limited_reach, pipeline_inputs
    from scipy.spatial.transform import Rotation

    from model.geometry import to_matrix
    from service import registration
    from service.registration import Network

    rng = np.random.default_rng(3)
    hub = rng.uniform(-0.5, 0.5, (1500, 2))
    hub = hub[np.linalg.norm(hub, axis=1) < 0.5]
    parts = [np.column_stack([hub, np.zeros(len(hub))])]  # a flat disc
    for k in range(3):  # bars off the axis, each sampled on its own: no mirror, no exact copy
        turn = Rotation.from_euler("z", 120 * k, degrees=True).as_matrix()
        parts.append(rng.uniform([0.4, 0.0, 0.0], [1.6, 0.3, 0.4], size=(900, 3)) @ turn.T)
    parts.append(rng.uniform([1.3, 0.0, 0.4], [1.6, 0.3, 0.9], size=(600, 3)))  # the marker
    source = np.concatenate(parts)
    centre = source.mean(axis=0)
    third = Rotation.from_euler("z", 120, degrees=True).as_matrix()
    wrong = (third, centre - third @ centre)
    monkeypatch.setattr(registration, "feature_match", lambda *args: wrong)
    turns = []
    options, settings, _ = pipeline_inputs(None, None, method="auto", refine={}, init=to_matrix(*wrong).tolist())
    draft = Network("object", 384, limited_reach(turns), "draft")
    networks = [Network("object", 768, limited_reach(turns), draft=draft)]
    answer = asyncio.run(registration.register_clouds(source, source, options, settings, networks))
    assert len(turns) == 1 + len(registration.STARTS) and turns[0] > 45.0  # the draft once, then the starts
    assert (answer.stage, answer.verified) == ("multistart", True), answer.reason
    assert rotation_angle_deg(answer.rotation, np.eye(3)) < 0.01 and answer.fitness > 0.99


def room(rng: np.random.Generator, boxes: list[tuple[float, float]], count: int = 6000) -> np.ndarray:
    """A floor and a back wall along x in [0, 6], boxes (x centre, width) standing against the wall."""
    floor = np.column_stack([rng.uniform(0, 6, count), rng.uniform(0, 2, count), np.zeros(count)])
    wall = np.column_stack([rng.uniform(0, 6, count // 2), np.full(count // 2, 2.0), rng.uniform(0, 1, count // 2)])
    parts = [floor, wall]
    for centre, width in boxes:
        box = np.column_stack(
            [rng.uniform(centre - width / 2, centre + width / 2, count // 10), rng.uniform(1.6, 2.0, count // 10)]
        )
        box = np.column_stack([box, rng.uniform(0, 0.4, len(box))])
        face = rng.integers(0, 3, len(box))  # the front, the top or a side
        box[face == 0, 1], box[face == 1, 2] = 1.6, 0.4
        box[face == 2, 0] = centre + np.where(rng.random((face == 2).sum()) < 0.5, -width, width) / 2
        parts.append(box)
    return np.concatenate(parts)


def stepped_wall(rng: np.random.Generator, count: int = 6000) -> np.ndarray:
    """A floor and a back wall along x in [0, 6] whose height steps irregularly, with a fin standing
    out of the wall at every step: no slide repeats it."""
    steps, heights = [0.0, 0.7, 1.1, 2.4, 2.9, 3.3, 4.5, 5.2, 6.0], [0.5, 1.0, 0.3, 0.8, 0.6, 1.2, 0.4, 0.9]
    parts = [np.column_stack([rng.uniform(0, 6, count // 2), rng.uniform(0, 2, count // 2), np.zeros(count // 2)])]
    for start, end, height in zip(steps[:-1], steps[1:], heights, strict=True):
        size, fin = int(count * (end - start) / 6 * height), count // 20
        parts.append(np.column_stack([rng.uniform(start, end, size), np.full(size, 2.0), rng.uniform(0, height, size)]))
        parts.append(np.column_stack([np.full(fin, end), rng.uniform(1.7, 2.0, fin), rng.uniform(0, height, fin)]))
    return np.concatenate(parts)


def prepared_pair(source, target):
    from conftest import pipeline_inputs

    from service import registration

    options, settings, _ = pipeline_inputs(None, None, method="auto", refine={})
    return registration._prepare(source, target, 384, options, settings), options


def two_captures(scene):
    """Two captures of a scene, x <= 4 and x >= 2 (half of the source overlaps), the second moved:
    the pair made ready as `auto` makes it, the options, and the true rotation and translation."""
    rng = np.random.default_rng(0)
    first, second = scene(rng), scene(rng)
    rotation, translation = euler_to_matrix([5.0, 3.0, -4.0]), np.array([0.2, -0.1, 0.05])
    target = apply_transform(second[second[:, 0] >= 2], rotation, translation)
    return *prepared_pair(first[first[:, 0] <= 4], target), rotation, translation


def checked_answer(prepared, options, rotation, translation):
    """An answer at (R, t), refined and checked as the pipeline refines and checks its answers."""
    from service import registration
    from service.schemas import RefineOptions

    candidate = registration._checked(prepared, rotation, translation, RefineOptions())
    return registration._result(prepared, candidate, "features", "object", options, dict(registration._FREE))


def slid_sample(prepared, options, rotation, translation):
    """The sample pair's truth slid by a tenth of the extent along the target's longest axis, refined
    and checked; and the extent."""
    cloud = prepared.check.target
    size = extent(cloud)
    longest = principal_axes(cloud)[:, -1]
    return checked_answer(prepared, options, rotation, translation + 0.1 * size * longest), size


def test_a_right_answer_with_no_better_pose_beside_it_stays_verified():
    from service import registration

    prepared, options, rotation, translation = two_captures(stepped_wall)
    answer = checked_answer(prepared, options, rotation, translation)
    assert answer.verified and answer.fitness < registration.SLIDE_FITNESS  # half of it overlaps: it is looked at
    assert registration._unless_slid(prepared, answer, options, None) is answer


def test_an_answer_of_the_rotated_starts_needs_a_closer_fit(monkeypatch):
    """A rotated start's answer (and a half turn's) is verified only where it matches at least
    MIN_STARTS_FITNESS of the source both ways: the same right pose passes as one method's answer
    and fails as a start's when the bar lies above its fit."""
    from service import registration

    prepared, options, rotation, translation = two_captures(stepped_wall)
    answer = registration._checked(prepared, rotation, translation, None)
    assert answer.verification.verified
    fit = min(answer.verification.score.fitness, answer.verification.score.overlap)
    monkeypatch.setattr(registration, "MIN_STARTS_FITNESS", fit - 0.01)
    (start,) = registration._rivals(prepared, [(rotation, translation)], options, [])
    assert start.verification.verified
    monkeypatch.setattr(registration, "MIN_STARTS_FITNESS", fit + 0.01)
    (start,) = registration._rivals(prepared, [(rotation, translation)], options, [])
    assert not start.verification.verified and "needed" in start.verification.reason


def test_a_network_answer_no_feature_match_confirms_must_match_more_to_stay_verified():
    """A network's verified answer matching under UNCORROBORATED_MIN_FITNESS of the source is given
    unverified where feature matching's guess does not confirm it (a TUM room view's local minimum,
    3.7 deg and 0.49 m off, fits 0.30 and passes the check); confirmed, or matching more, or feature
    matching's own, it stays verified."""
    import dataclasses

    from service import registration

    prepared, options, rotation, translation = two_captures(stepped_wall)
    answer = dataclasses.replace(checked_answer(prepared, options, rotation, translation), stage="ifnet")
    assert answer.verified
    low = dataclasses.replace(answer, score=answer.score._replace(fitness=0.35))
    far = registration._FeatureGuess(euler_to_matrix([90.0, 0.0, 0.0]) @ rotation, translation, 0.01, 0.1)
    near = dataclasses.replace(far, rotation=rotation)
    flagged = registration._unless_uncorroborated(low, far)
    assert not flagged.verified and "no second opinion" in flagged.reason and flagged.rotation is low.rotation
    assert not registration._unless_uncorroborated(low, None).verified
    assert registration._unless_uncorroborated(low, near) is low
    assert registration._unless_uncorroborated(answer, far) is answer  # it matches more than 0.4
    assert registration._unless_uncorroborated(dataclasses.replace(low, stage="features"), far).verified


def test_a_far_start_on_a_thinned_scan_skips_the_fine_pass(monkeypatch):
    """On clouds thinned for the check and with nothing verified, a start's answer that still matches
    under FINE_PASS_MIN_FITNESS after the coarse pass is checked without the fine pass on the check's
    8,000 points; the right pose gets both passes, and so does the far one where it judges a verified
    answer (skipped, a right rival could leave a wrong answer verified)."""
    from model.geometry import AlignmentClouds
    from service import registration

    rng = np.random.default_rng(0)
    scene = stepped_wall(rng, 24_000)
    rotation, translation = euler_to_matrix([5.0, 3.0, -4.0]), np.array([0.2, -0.1, 0.05])
    prepared, options = prepared_pair(scene, apply_transform(stepped_wall(rng, 24_000), rotation, translation))
    assert prepared.coarse is not prepared.check  # thinned: the coarse pass runs on fewer points
    passes, refine = [], AlignmentClouds.refine
    monkeypatch.setattr(
        AlignmentClouds, "refine", lambda clouds, *args, **kw: passes.append(clouds) or refine(clouds, *args, **kw)
    )
    far = euler_to_matrix([150.0, 40.0, -70.0]) @ rotation

    def refined_on(pose, settled=()) -> list[str]:
        passes.clear()
        registration._rivals(prepared, [pose], options, list(settled), anyway=len(settled))
        return ["check" if clouds is prepared.check else "coarse" for clouds in passes]

    assert refined_on((far, translation)) == ["coarse"]
    assert refined_on((rotation, translation)) == ["coarse", "check", "check"]  # the check refines once more
    judged = checked_answer(prepared, options, rotation, translation)
    assert refined_on((far, translation), [judged])[:2] == ["coarse", "check"]
    monkeypatch.setattr(registration, "FINE_PASS_MIN_FITNESS", 0.0)
    assert refined_on((far, translation))[:2] == ["coarse", "check"]


def test_probes_that_come_back_to_the_answer_stop_after_their_coarse_pass(monkeypatch):
    """Beside a right answer most probes' coarse pass leads back to it: their fine pass, which would
    settle them there, is skipped, and every pass of a probe stops at SLIDE_ITERATIONS."""
    from service import registration

    prepared, options, rotation, translation = two_captures(stepped_wall)
    answer = checked_answer(prepared, options, rotation, translation)
    calls = small_refinements(monkeypatch)
    assert registration._unless_slid(prepared, answer, options, None) is answer
    probes = len(
        slides(answer.translation, prepared.check.target, registration.SLIDE_SHARES, registration.SLIDE_DIAGONAL_SHARES)
    )
    passes = [iterations for points, iterations in calls if points <= registration.SLIDE_POINTS]
    assert probes <= len(passes) < 2 * probes
    assert set(passes) == {registration.SLIDE_ITERATIONS}


def small_refinements(monkeypatch):
    """The AlignmentClouds.refine calls from now on, as (source points, iteration cap): the slide check's
    probes run on SLIDE_POINTS."""
    from model.geometry import AlignmentClouds

    calls = []
    refine = AlignmentClouds.refine

    def counted(self, *args, **kwargs):
        calls.append((len(self.source), kwargs.get("max_iterations")))
        return refine(self, *args, **kwargs)

    monkeypatch.setattr(AlignmentClouds, "refine", counted)
    return calls


def test_feature_matching_landing_on_an_answer_it_did_not_start_spares_the_look_beside_it(monkeypatch):
    """Feature matching's guess within SLIDE_GUESS_SHARE of the extent and AGREEMENT_DEG of a network's
    answer: an independent method found the same place, so no probe runs. A guess further off, or an
    answer refined from the guess itself (stage `features`), is looked beside as before."""
    import dataclasses

    from scipy.spatial.transform import Rotation

    from service import registration

    prepared, options, rotation, translation = two_captures(stepped_wall)
    answer = dataclasses.replace(checked_answer(prepared, options, rotation, translation), stage="draft")
    assert answer.verified and answer.fitness < registration.SLIDE_FITNESS
    extent = prepared.check.target_extent
    turn = Rotation.from_rotvec([0.0, 0.0, np.radians(3.0)]).as_matrix()  # about the origin: the centre moves too
    centre = prepared.check.source_centre

    def guess(share):
        turned = turn @ answer.rotation
        # the source's centre `share` of the extent from where the answer puts it
        moved = answer.rotation @ centre + answer.translation + np.array([share * extent, 0.0, 0.0])
        return registration._FeatureGuess(turned, moved - turned @ centre, 0.01, prepared.check.spacing)

    probed = small_refinements(monkeypatch)
    assert registration._unless_slid(prepared, answer, options, guess(0.005)) is answer
    assert not probed
    for judged, near in [(answer, guess(0.02)), (dataclasses.replace(answer, stage="features"), guess(0.005))]:
        assert registration._unless_slid(prepared, judged, options, near) is judged
        assert sum(size <= registration.SLIDE_POINTS for size, _ in probed) >= len(registration.SLIDE_SHARES) * 6
        probed.clear()


def test_a_verified_pose_slid_beside_the_truth_gives_way_to_it_flagged():
    """On the sample pair, the truth slid by a tenth of the extent along the target's longest axis and
    refined still passes the check, matching 0.4-0.5 of the source where the truth matches 0.8. A slide
    back finds the truth: it is given, not verified, since both pass."""
    from service import registration

    source, target, truth = sample_pair(turned=False)
    prepared, options = prepared_pair(source, target)
    rotation, translation = from_matrix(truth)
    slid, extent = slid_sample(prepared, options, rotation, translation)
    assert slid.verified and np.linalg.norm(slid.translation - translation) > 0.05 * extent  # wrong, and verified
    answer = registration._unless_slid(prepared, slid, options, None)
    assert not answer.verified and answer.reason.startswith("ambiguous: a pose")
    assert np.linalg.norm(answer.translation - translation) < 0.01 * extent
    assert rotation_angle_deg(answer.rotation, rotation) < 0.5 and answer.fitness > 1.5 * slid.fitness
    assert answer.timings_ms["postprocess_ms"] > slid.timings_ms["postprocess_ms"]


@pytest.mark.parametrize("threshold", [1e-4, 10.0], ids=["tiny", "huge"])
def test_a_users_fitness_threshold_changes_what_is_reported_not_the_verdict(threshold):
    """The request's fitness_threshold sets the reported fitness only: the slid pose of the sample pair
    is still looked beside and flagged (at 10 units every pose would match the whole source, and
    an answer matching 0.85 or more is not looked beside), and the truth still stands."""
    from service import registration

    source, target, truth = sample_pair(turned=False)
    prepared, default = prepared_pair(source, target)
    own = default.model_copy(update={"fitness_threshold": threshold})
    rotation, translation = from_matrix(truth)
    for options in (default, own):
        slid, _ = slid_sample(prepared, options, rotation, translation)
        right = checked_answer(prepared, options, rotation, translation)
        judged = registration._unless_slid(prepared, slid, options, None)
        assert not judged.verified and judged.reason.startswith("ambiguous: a pose"), options.fitness_threshold
        assert registration._unless_slid(prepared, right, options, None) is right and right.verified
        assert registration._given([slid, right], "auto").translation is right.translation
    assert slid.fitness_threshold == threshold and slid.fitness in (0.0, 1.0)  # reported at the user's distance


def test_on_evenly_spaced_shelves_the_right_answer_is_flagged_ambiguous():
    """Where the scene repeats itself, a pose one box along fits better than the truth: neither is verified."""
    from service import registration

    prepared, options, rotation, translation = two_captures(
        lambda rng: room(rng, [(0.25 + 0.5 * k, 0.2) for k in range(12)])
    )
    answer = checked_answer(prepared, options, rotation, translation)
    assert answer.verified
    judged = registration._unless_slid(prepared, answer, options, None)
    assert not judged.verified and "ambiguous" in judged.reason


def with_outliers(points: np.ndarray, share: float, rng: np.random.Generator) -> np.ndarray:
    """The points and share x as many more, uniform in their bounding box."""
    outliers = rng.uniform(points.min(axis=0), points.max(axis=0), size=(int(share * len(points)), 3))
    return np.concatenate([points, outliers])


def test_outliers_alone_do_not_send_a_draft_answer_to_the_rotated_starts(monkeypatch):
    """A pinwheel turned 150 deg, the request's `init` at the truth, a fifth more points as outliers
    in the source: the draft's answer there is verified and matches less than SLIDE_FITNESS of the
    source, but all of its surfaces, so the half turns judge it and the rotated starts do not."""
    import asyncio

    from conftest import pipeline_inputs

    from model.geometry import to_matrix
    from service import registration
    from service.batcher import Prediction
    from service.registration import Network

    rng = np.random.default_rng(3)
    shape = pinwheel(3, rng)
    truth = euler_to_matrix([150.0, 20.0, -30.0])
    source, target = with_outliers(shape, 0.2, rng), shape @ truth.T
    monkeypatch.setattr(registration, "feature_match", lambda *args: (truth, np.zeros(3)))
    calls = []

    async def stays(source_n, target_n):
        calls.append(len(source_n))
        return Prediction(np.eye(3), np.zeros(3))

    init = to_matrix(truth, np.zeros(3)).tolist()
    options, settings, _ = pipeline_inputs(None, None, method="auto", refine={}, init=init)
    networks = [Network("object", 768, stays, draft=Network("object", 384, stays, "draft"))]
    answer = asyncio.run(registration.register_clouds(source, target, options, settings, networks))
    assert (answer.stage, answer.verified) == ("draft", True), answer.reason
    assert rotation_angle_deg(answer.rotation, truth) < 0.01
    assert answer.fitness < registration.SLIDE_FITNESS
    assert calls == [384]  # the draft once; no start asked


@pytest.mark.parametrize("overlap", ["whole", "half"])
def test_outliers_alone_do_not_send_a_right_answer_to_the_slide_check(monkeypatch, overlap):
    """Outliers in the source lower the right answer's fitness below SLIDE_FITNESS, not the share of
    the source's surfaces it lays on the target's: with the whole scene in both clouds (one capture,
    moved) that share stays above it and no probe is tried; with half of it, probes are tried."""
    from service import registration

    rng = np.random.default_rng(3)
    first = second = stepped_wall(rng)
    rotation, translation = euler_to_matrix([5.0, 3.0, -4.0]), np.array([0.2, -0.1, 0.05])
    if overlap == "half":
        first, second = first[first[:, 0] <= 4], second[second[:, 0] >= 2]
    source, target = with_outliers(first, 0.2, rng), apply_transform(second, rotation, translation)
    prepared, options = prepared_pair(source, target)
    answer = checked_answer(prepared, options, rotation, translation)
    surfaces = prepared.check.surface_fitness(answer.rotation, answer.translation)
    assert answer.verified and answer.fitness < registration.SLIDE_FITNESS
    assert (surfaces >= registration.SLIDE_FITNESS) == (overlap == "whole")
    probes = small_refinements(monkeypatch)
    assert registration._unless_slid(prepared, answer, options, None) is answer
    assert bool(probes) == (overlap == "half")


def test_only_a_verified_answer_that_matches_little_is_looked_beside(monkeypatch):
    """The slide check leaves an answer matching SLIDE_FITNESS of the source or more, and an unverified
    one, as they are, without a look; every answer register_clouds gives passes through it."""
    import asyncio

    from conftest import pipeline_inputs

    from service import registration
    from service.registration import Network

    source, target, truth = sample_pair(turned=False)
    prepared, options = prepared_pair(source, target)
    rotation, translation = from_matrix(truth)
    right = checked_answer(prepared, options, rotation, translation)
    slid, extent = slid_sample(prepared, options, rotation, translation)
    unverified = checked_answer(prepared, options, rotation, translation + np.array([0.0, 0.0, extent]))
    monkeypatch.setattr(registration, "SLIDE_FITNESS", right.fitness)  # the sample's truth matches 0.81 of it
    assert right.fitness >= registration.SLIDE_FITNESS > slid.fitness and slid.verified and not unverified.verified
    for left in (right, unverified):
        assert registration._unless_slid(prepared, left, options, None) is left
    assert registration._unless_slid(prepared, slid, options, None) is not slid
    handed = []
    monkeypatch.setattr(
        registration, "_unless_slid", lambda prepared, answer, options, guess: handed.append(answer) or answer
    )
    _, settings, _ = pipeline_inputs(None, None)
    for given in (right, slid, unverified):

        async def answer(*args, given=given):
            return given, None

        monkeypatch.setattr(registration, "_answer", answer)
        asyncio.run(registration.register_clouds(source, target, options, settings, [Network("object", 384, None)]))
    assert handed == [right, slid, unverified]


def test_verdicts_are_those_a_request_would_get():
    """The calibration's entry: the check, then the slide check, on the caller's poses."""
    from service import registration
    from service.settings import Settings

    source, target, truth = sample_pair(turned=False)
    prepared, options = prepared_pair(source, target)
    rotation, translation = from_matrix(truth)
    slid, extent = slid_sample(prepared, options, rotation, translation)
    far = (rotation, translation + np.array([0.0, 0.0, extent]))
    right, flagged, unverified = registration.verdicts(
        source, target, [(rotation, translation), (slid.rotation, slid.translation), far], Settings()
    )
    assert right.verified and not unverified.verified
    assert not flagged.verified and flagged.reason.startswith("ambiguous")
    assert np.linalg.norm(flagged.translation - translation) < 0.01 * extent


@pytest.mark.parametrize(
    ("axis", "degrees"),
    [([0.16, -0.82, 0.55], 180.0), ([0.74, 0.54, -0.4], 87.0)],
    ids=["half-turn", "quarter-turn"],
)
@pytest.mark.parametrize("method", ["ifnet", "auto"])
async def test_a_wrong_pose_the_check_passes_given_as_init_is_not_the_verified_answer(
    serve, shipped_model, axis, degrees, method
):
    """The sample table's truth turned about an axis through the overlap's centre and refined as the
    service refines settles on a wrong pose (180 and 61 deg off) that the check and the slide check
    pass (fitness 0.70 and 0.48 against the truth's 0.81): they cannot tell it from the truth. Sent as the request's
    `init`, the network starts there: alone (`ifnet`) it stays there, and feature matching's
    answer must contradict it (without that rule it is verified); `auto` must find the truth or
    flag its answer."""
    from scipy.spatial.transform import Rotation

    from model.geometry import AlignmentClouds, Normalisation, to_matrix
    from service import registration

    source, target, truth = sample_pair(turned=False)
    clouds = AlignmentClouds(source, target)
    centre = apply_transform(source, *from_matrix(truth)).mean(axis=0)
    turn = Rotation.from_rotvec(np.radians(degrees) * np.asarray(axis) / np.linalg.norm(axis)).as_matrix()
    rotation, translation = turn @ truth[:3, :3], turn @ (truth[:3, 3] - centre) + centre
    for distance in registration.refine_distances(clouds.spacing, Normalisation(source, target).scale):
        rotation, translation, _ = clouds.refine(rotation, translation, distance)
    (verdict,) = registration.verdicts(source, target, [(rotation, translation)], Settings())
    assert verdict.verified and rotation_angle_deg(rotation, truth[:3, :3]) > 45  # the check alone is fooled
    async with serve(Settings(model_path=shipped_model, warmup=False)) as (_, client):
        init = to_matrix(rotation, translation).tolist()
        answer = await register(client, source, target, method=method, init=init, refine=True)
    assert rotation_error(answer, truth) < 2.0 or answer["verified"] is False, answer


def pinwheel(bars: int, rng: np.random.Generator) -> np.ndarray:
    """A flat disc with `bars` bars off its axis, each sampled on its own, and a marker on one: a turn
    by one bar's spacing about the axis fits all but the marker."""
    from scipy.spatial.transform import Rotation

    hub = rng.uniform(-0.5, 0.5, (1500, 2))
    hub = hub[np.linalg.norm(hub, axis=1) < 0.5]
    parts = [np.column_stack([hub, np.zeros(len(hub))])]
    for k in range(bars):
        turn = Rotation.from_euler("z", 360.0 * k / bars, degrees=True).as_matrix()
        parts.append(rng.uniform([0.5, -0.05, 0.0], [2.0, 0.05, 0.3], size=(400, 3)) @ turn.T)
    parts.append(rng.uniform([1.6, -0.05, 0.3], [2.0, 0.05, 0.8], size=(600, 3)))
    return np.concatenate(parts)


@pytest.mark.parametrize("polished", [True, False])
def test_a_starts_answer_in_a_local_minimum_gives_way_to_the_better_pose_beside_it(monkeypatch, polished):
    """A pinwheel of 12 bars: turned by one bar (30 deg) it fits all but the marker, and refinement
    stays there; that pose passes the check. Feature matching finds nothing, and the one rotated start
    within the network's reach lands on that turn. Turned 20 deg back about the pinwheel's axis, it
    refines into the truth, which fits better with tighter inliers: the answer, verified. Without
    that look, the turned pose would be the verified answer."""
    import asyncio

    from conftest import kabsch, pipeline_inputs
    from scipy.spatial.transform import Rotation

    from service import registration
    from service.batcher import Prediction
    from service.registration import Network

    if not polished:
        monkeypatch.setattr(registration, "POLISHED_STAGES", ())
    source = pinwheel(12, np.random.default_rng(4))
    by_a_bar = Rotation.from_euler("z", 30.0, degrees=True).as_matrix()
    away = np.array([50.0, 0.0, 0.0])  # far off the target: nothing to refine, fails the check
    monkeypatch.setattr(registration, "feature_match", lambda *args: (np.eye(3), away))

    async def off_by_a_bar(source_n, target_n):
        rotation, _ = kabsch(source_n.astype(np.float64), target_n.astype(np.float64))
        if rotation_angle_deg(rotation, np.eye(3)) > 45.0:
            return Prediction(np.eye(3), away)
        return Prediction(by_a_bar @ rotation, np.zeros(3))  # the clouds are centred on the pinwheel's centroid

    options, settings, _ = pipeline_inputs(None, None, method="global", refine={})
    networks = [Network("object", 384, off_by_a_bar)]
    answer = asyncio.run(registration.register_clouds(source, source, options, settings, networks))
    assert (answer.stage, answer.verified) == ("multistart", True), answer.reason
    error = rotation_angle_deg(answer.rotation, np.eye(3))
    if polished:
        assert error < 0.01 and answer.fitness > 0.99
    else:
        assert abs(error - 30.0) < 1.0 and answer.fitness < 0.95


@pytest.mark.parametrize("anyway", [1, 0])
def test_judging_the_best_start_is_refined_even_where_it_fits_loosely_under_the_bar(anyway):
    """The box with a block, its flipped pose verified (the block aside, it fits). The network missed
    from every start but one, which lands 30 deg off the truth: loosely it fits under 0.8 as well
    as the flipped pose, so it is no rival to refine; but as the best start it is refined anyway,
    into the truth, which fits better with tighter inliers and is the answer, verified. Without that,
    nothing judges the flipped pose and it stays the verified answer."""
    from conftest import pipeline_inputs

    from service import registration
    from service.batcher import Prediction
    from service.registration import LOOSE_SPACINGS, _checked, _given, _prepare, _result
    from service.schemas import RefineOptions

    source, truth, flipped = box_with_a_block()
    options, settings, _ = pipeline_inputs(384, None, refine={}, method="global")
    prepared = _prepare(source, source, 384, options, settings)
    centre = source.mean(axis=0)

    def about_centre(rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return rotation, centre - rotation @ centre

    flip = truth.T @ flipped  # half a turn about the box's short axis
    wrong = _result(prepared, _checked(prepared, *about_centre(flip), RefineOptions()), "draft", "object", options, {})
    assert wrong.verified
    near = euler_to_matrix([30.0, 0.0, 0.0])
    bar = registration.RIVAL_LOOSE_SHARE * prepared.check.fitness(prepared.scored, *about_centre(flip), LOOSE_SPACINGS)
    assert prepared.check.fitness(prepared.scored, *about_centre(near), LOOSE_SPACINGS) < bar
    far_away = np.array([50.0, 0.0, 0.0])  # in the network's frame: matches nothing
    predictions = [Prediction(near @ start.T, np.zeros(3)) for start in registration.STARTS[:1]]
    predictions += [Prediction(start.T, far_away) for start in registration.STARTS[1:]]
    found, _ = registration._finish_multistart(prepared, predictions, "object", options, [wrong], anyway)

    answer = _given([wrong, *found], "global")
    assert answer.verified, answer.reason
    if anyway:
        assert answer.stage == "multistart" and rotation_angle_deg(answer.rotation, np.eye(3)) < 0.01
    else:
        assert found == [] and answer is wrong


# Views (bench.harness.scan_pair's name and seed) where the check passes a wrong pose, so only the rest
# of the pipeline keeps it from being verified: a TUM room, once verified 3.7 deg and 0.49 m off (a local
# minimum feature matching's refined guess "confirmed": CONFIRMING_BETTER_FIT), and a synthetic living
# room whose pose 120 deg off passes. Both were verified wrong with feature matching's voxel at 5
# point spacings of a thinned scan instead of THINNED_FEATURE_SPACINGS.
RISKY_VIEWS = [
    ("indoor_scans/tum__tum-o3d-sample__TUM_depth", 3),
    ("indoor_scans/iclnuim__iclnuim-slambook2__4", 0),
    ("indoor_scans/iclnuim__iclnuim-slambook2__4", 1),
]


def auto_answer(pair, settings: Settings, networks):
    """`auto` with `refine` on the pair in process, one step after another, as bench.ab runs it."""
    import asyncio

    from bench import ab
    from service.registration import register_clouds
    from service.schemas import RefineOptions, RegistrationOptions

    options = RegistrationOptions(method="auto", refine=RefineOptions())
    return asyncio.run(
        register_clouds(pair.source, pair.target, options, settings, networks, ab.in_turn, settings.threads)
    )


@pytest.mark.slow
@pytest.mark.parametrize("turn_deg", [[90.0, 0.0, 0.0], [0.0, -5.0, 0.0]], ids=["missed", "beside"])
def test_auto_flags_a_local_minimum_no_feature_match_confirms(monkeypatch, turn_deg):
    """The TUM room view of RISKY_VIEWS with feature matching's guess turned 90 deg away (KISS-Matcher's
    answer differs from run to run, and once missed there) or 5 deg, within AGREEMENT_DEG of a local
    minimum 3.7 deg off that passes the check and fits 0.30: neither the model's nor the draft's answer
    there is given verified."""
    from conftest import SHARED_DATA

    from bench import ab, harness
    from service import registration

    if not (SHARED_DATA / "indoor_scans.npz").is_file():
        pytest.skip(f"real scans not found in {SHARED_DATA} (shared data is not checked out here)")
    matched, turn = registration.feature_match, euler_to_matrix(turn_deg)

    def missed(source, target, spacing, spacings):
        rotation, translation = matched(source, target, spacing, spacings)
        centre = target.mean(axis=0)
        return turn @ rotation, turn @ (translation - centre) + centre

    monkeypatch.setattr(registration, "feature_match", missed)
    settings = Settings()
    pair = harness.scan_pair(*RISKY_VIEWS[0])
    answer = auto_answer(pair, settings, ab.networks(settings))
    assert harness.errors(pair, answer.rotation, answer.translation)["right"] or not answer.verified


@pytest.mark.slow
def test_auto_is_right_or_flags_its_answer_on_real_scans():
    """`auto` with `refine`, as the service runs it, on the benchmark's views of real scans
    (bench.harness.scan_pair, seed 0), the real pairs with ground truth and RISKY_VIEWS: no wrong
    answer verified, and every pair with ground truth right."""
    from conftest import SHARED_DATA

    from bench import ab, harness

    if not (SHARED_DATA / "indoor_pairs.npz").is_file():
        pytest.skip(f"real scans not found in {SHARED_DATA} (shared data is not checked out here)")
    settings = Settings()
    networks = ab.networks(settings)
    views = [(name, 0) for name in harness.DEFAULT_SCANS] + RISKY_VIEWS
    pairs = {f"{name} seed {seed}": harness.scan_pair(name, seed) for name, seed in views}
    truth = {pair.name: pair for pair in harness.truth_pairs()}
    verdicts = {}
    for name, pair in (pairs | truth).items():
        answer = auto_answer(pair, settings, networks)
        verdicts[name] = (harness.errors(pair, answer.rotation, answer.translation)["right"], answer.verified)
    assert not [name for name, (right, verified) in verdicts.items() if verified and not right], verdicts
    assert all(verdicts[name][0] for name in truth), verdicts
