"""From two user clouds to a rigid transform in the user's units: the one pre/post-processing path.

`register_clouds` checks both clouds, removes exact duplicates (and reports how many), applies
the optional initial guess to the source, resamples each cloud to the network's point count,
centres each and scales both by one common factor to the network's radius
(`model.geometry.NETWORK_RADIUS`), asks the model (any async callable) for the transform between
the normalised clouds, maps it back into the user's units, composes it with the initial guess,
optionally refines it (GICP on up to CHECK_MAX_POINTS of each cloud) and checks it
(`model.geometry.verify_alignment`). Under `auto` the first model's draft network (the same
weights over fewer blocks and points, when the repository has one) is asked before the model, for
the source as it lies and, failing that, turned by feature matching's guess; its answer, always
refined, stands only when it passes the check and feature matching agrees with it (and where its
two answers both pass and disagree, the pair is ambiguous and no model is asked; where it fails the
check only because the clouds cannot pin the motion down and feature matching agrees, it stands
unverified); otherwise feature matching's answer, refined, is checked before any model is asked.
Where the method allows and the answer fails the check, the other networks follow in turn, then
the global path: feature matching (also a second opinion on a verified answer), then the first
network's draft (or the network) from 24 rotated starts, which also judge a verified answer: a
start that lands far from it and fits as well (a symmetric shape) contradicts it. Under `auto`
the starts do not search where an answer fails the check only on its constraint and matches most
of the source, and elsewhere replace such an answer only where they fit clearly better.
Whatever the path, a verified answer that matches little of the source, unless feature matching
landed on it independently, is slid back and forth beside itself: a pose there that fits clearly
better and passes the check too leaves the pair ambiguous (`_unless_slid`). `register_pairs` runs
a request's pairs through it and the models' batchers.
"""

import asyncio
import dataclasses
import time
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass
from typing import Any, Literal, TypeVar

import numpy as np
from scipy.spatial.transform import Rotation
from starlette.requests import Request

from model.geometry import (
    FEATURE_VOXEL_SPACINGS,
    INLIER_SPACINGS,
    MIN_FITNESS,
    REFINE_SPACINGS,
    AlignmentClouds,
    AlignmentScore,
    FarthestPoints,
    Normalisation,
    Verification,
    apply_transform,
    at_most,
    feature_match,
    fitness_and_rmse,
    from_matrix,
    nearest_rotation,
    point_spacing,
    resample_indices,
    rotation_angle_deg,
    slides,
    subset,
    to_matrix,
)
from service.batcher import Prediction, RequestTimeoutError
from service.features import FeatureMatch
from service.schemas import RefineOptions, RegistrationOptions, Sampling
from service.settings import Settings
from service.state import ServiceState
from service.validation import InvalidInput, check_cloud

# Feature matching, refinement and the check run on at most this many points per cloud (a seeded
# subset): their cost grows with it and small_gicp and KISS-Matcher hold the interpreter lock.
CHECK_MAX_POINTS = 8_000
REFINE_MAX_SECONDS = 10.0
# The refinement's first, coarse pass, in normalised units (clouds of radius NETWORK_RADIUS), on at
# most COARSE_POINTS per cloud: its wide correspondences make each iteration dear, and it only has to
# bring the answer within reach of the fine pass on the check's clouds.
COARSE_DISTANCE_NORMALISED = 0.05
COARSE_POINTS = 3_000
# The coarse pass's distance in point spacings, at most: on a scan far wider than its spacing (a
# LiDAR's rings) that share of its size spans metres, where GICP pulls a guess a degree off further off.
COARSE_MAX_SPACINGS = 20.0
# Feature matching's voxel follows each cloud's point spacing at up to this many points: the
# check's sparser subset would give it a voxel too coarse for some real scans (docs/training/scenes.md).
FEATURE_SPACING_POINTS = 20_000
# Their voxel spans this many of those spacings: the matcher gets the check's sparser subset of a
# real scan, whose noise wants wider features than the default 1.5 (service/README.md).
THINNED_FEATURE_SPACINGS = 3.5
# Where its answer on the check's subset of a larger cloud fails the check, it matches once more on up
# to this many points of each cloud: on a LiDAR scan's rings the subset leaves it lost more often.
WIDER_FEATURE_POINTS = 20_000
# The global path's starts: the 24 rotations of a cube, every rotation within the network's range
# of one of them; the network's answers from the best few (by fitness) are refined and checked.
STARTS = Rotation.create_group("O").as_matrix()
STARTS_REFINED = 3
# Starts judging verified answers refine their rivals: starts further than RIVAL_REACH_DEG from each
# (nearer ones settle on it) that fit at least RIVAL_LOOSE_SHARE as well as it at LOOSE_SPACINGS
# point spacings, forgiving a coarse answer's few degrees (on real scans no start comes near); and
# the best STARTS_JUDGING_ANYWAY of those far from them whatever their loose fit: where the network
# misses from every start (a jittered shape of an unseen class), one 30-50 deg off the truth fits
# loosely under that bar and refines into it. Where feature matching vouches for no verified answer,
# the best UNCORROBORATED_JUDGING_ANYWAY of them (past STARTS_REFINED): on an unseen shape with
# outliers many poses pass the check, and the truth was the tenth best start.
RIVAL_REACH_DEG = 15.0
LOOSE_SPACINGS = 4.5
RIVAL_LOOSE_SHARE = 0.8
STARTS_JUDGING_ANYWAY = 1
UNCORROBORATED_JUDGING_ANYWAY = 10
# The draft's first answer, set aside far from feature matching's guess, is refined to judge the answer
# from the guess's turn only where it fits loosely at least this share as well: refined, those fitting
# less never contradicted it, and refining them cost most on large scans (service/README.md).
CONTRADICTING_LOOSE_SHARE = 0.4
STARTS_SCORE_POINTS = 2_000  # check source points that rank coarse answers (starts, half turns, slides)
# Points per cloud of the starts' network calls: a coarse answer each, which refinement settles;
# each call costs about 0.4x one at the network's 768 points.
STARTS_POINTS = 384
# Their answers (and the half turns') are verified only where they match at least this of the source
# both ways: of many turns tried, one that fits a third of a partial scan may be wrong.
MIN_STARTS_FITNESS = 0.4
# Where the coarse pass runs on a subset of the check's clouds and nothing verified is to be judged, a
# coarse answer (a rotated start's, a network's or its draft's under `auto`) matching under this share
# of the source at LOOSE_SPACINGS after it skips the fine pass: far off, each fine iteration searched
# 8,000 points' neighbours far from any surface (up to 0.8 s an answer on a tabletop). Of real-scan
# truths turned 3-40 deg (bench.fine_pass), none that ended right and verified or right and unpinned
# had matched under 0.24 there (at INLIER_SPACINGS, some under 0.05).
FINE_PASS_MIN_FITNESS = 0.2
AGREEMENT_DEG = 5.0  # two fitting answers further apart than this contradict each other
# An unpinned answer whose translation puts the source's centre further than this share of the extent
# from where feature matching's guess puts it may have slid off the truth: the guess's turn alone
# does not confirm it (_confirmed_draft).
UNPINNED_AGREEMENT_SHARE = 0.05
# Under `auto`, an unpinned answer matching at least this share of the source leaves the next models and
# the rotated starts nothing to find: on tabletop scenes they only added answers the clouds pin down no
# better, or flips fitting a little better (service/README.md). On scans thinned for the check, two
# views overlap in part: there the starts found nothing at 0.48-0.53 in 2-4 s a view on a tabletop.
UNPINNED_FITNESS = 0.85
UNPINNED_FITNESS_THINNED = 0.4
# A draft's answer further than this from feature matching's guess is set aside unrefined: refinement
# would not bring the two within AGREEMENT_DEG (a draft's answer is 4-15 deg off on ModelNet, median).
DRAFT_REACH_DEG = 30.0
# The networks learnt turns of up to this per axis: a draft's answer turned further from `init` may be
# the guess's, a symmetric shape's turned pose, so it is judged before it stands (_answer); and only a
# guess turning the source further is worth asking the draft again (_confirmed_draft).
NETWORK_REACH_DEG = 45.0
# A verified answer matching less than SLIDE_FITNESS of the source, and of its surfaces (outliers lower the
# fitness, not the overlap: AlignmentClouds.surface_fitness), may lie beside the truth, slid along
# the surfaces where part of the clouds still overlaps (refined there, the check passes it): it is slid
# back and forth by each of SLIDE_SHARES of the extent along each principal axis of the target and by
# each of SLIDE_DIAGONAL_SHARES between two axes, refined on SLIDE_POINTS points (coarse to fine, for
# at most SLIDE_ITERATIONS per pass, the fine pass skipped where the coarse one leads back to the
# answer); a pose fitting SLIDE_MARGIN better that passes the check in full makes the pair
# ambiguous (_unless_slid). Three shares: a refined slide stops anywhere from beside the truth to a
# fifth of the extent, and a probe overshooting the truth settles beside it again.
SLIDE_FITNESS = 0.85
SLIDE_SHARES = (0.05, 0.1, 0.2)
SLIDE_DIAGONAL_SHARES = (0.05, 0.1)  # where no slide along one axis refines into the truth
SLIDE_POINTS = 500
SLIDE_MARGIN = 0.1
SLIDE_RETURN_SHARE = 0.01  # a probe whose coarse pass brings it this near the answer is back in its basin
SLIDE_ITERATIONS = 10  # per pass of a probe: on SLIDE_POINTS points GICP often cycles until its cap
# Feature matching's guess this near an answer it did not start rules a slide out: an independent method
# landed on the same place (calibration's slid poses lie at least twice as far from it).
SLIDE_GUESS_SHARE = 0.01
RIVAL_FITNESS_MARGIN = 0.05  # an unverified answer fitting within this of a verified one also contradicts it
RIVAL_RMSE_SHARE = 0.8  # a verified answer this much tighter than a verified rival, and fitting as well, outranks it
# A network's verified answer that feature matching does not confirm is given verified only where it matches
# at least this share of the source, as a rotated start's must (MIN_STARTS_FITNESS): on a TUM room view a
# local minimum 3.7 deg off fits 0.30 and passes the check, and where feature matching missed, nothing judged it.
# Under it, a guess within AGREEMENT_DEG confirms the draft's answer only refined (_confirmed_draft).
UNCORROBORATED_MIN_FITNESS = MIN_STARTS_FITNESS
CONFIRMING_BETTER_FIT = 0.05  # feature matching's refined answer fitting this much better confirms nothing
# A start's answer, refined from up to 63 degrees away, can settle in a local minimum that passes the check
# beside the truth: the answers of these stages are also refined from turns of POLISH_DEG about them.
POLISHED_STAGES = ("multistart",)
POLISH_DEG = 20.0
Stage = Literal["ifnet", "draft", "multistart", "features"]

T = TypeVar("T")
Predict = Callable[[np.ndarray, np.ndarray], Awaitable[Prediction]]
RunBlocking = Callable[..., Awaitable[Any]]


class RegistrationFailed(RuntimeError):
    """The model gave no usable transform for valid-looking input (e.g. non-finite numbers)."""


class ClientDisconnected(Exception):
    """The client went away before its answer was ready."""


@dataclass(frozen=True)
class Network:
    """One model's network as the pipeline asks it."""

    model: str  # the model's name
    network_points: int  # points per cloud it is given
    predict: Predict  # normalised clouds -> transform (in production: the model's batcher)
    stage: Stage = "ifnet"  # "draft" for a model's draft network
    draft: "Network | None" = None  # asked before this one by `auto`, when this one is asked first
    # Starts a call that runs while the request does CPU work of its own (on fewer threads) and returns
    # once it has begun, with the future of its answer (None: the call waits for that work).
    start_beside: Callable[[np.ndarray, np.ndarray], Awaitable["asyncio.Future[Prediction]"]] | None = None


@dataclass(frozen=True)
class CloudReport:
    received: int
    duplicates_removed: int
    network_points: int
    upsampled: bool  # fewer distinct points than network_points: some were repeated


@dataclass(frozen=True)
class CloudReports:
    source: CloudReport
    target: CloudReport


@dataclass(frozen=True)
class RefineReport:
    max_distance: float
    iterations: int
    network_transform: np.ndarray  # 4x4, before refinement


@dataclass(frozen=True)
class RegistrationResult:
    """One pair's answer, named as the response (`schemas.RegisterResponse`) names it."""

    rotation: np.ndarray  # [3, 3]: target ~ source @ rotation.T + translation
    translation: np.ndarray  # [3], user units
    fitness: float
    inlier_rmse: float
    fitness_threshold: float
    verified: bool  # the answer passed the check (model.geometry.verify_alignment)
    reason: str | None  # why not, when verified is False
    unpinned: bool  # failed the check on the constraint alone (Verification.unpinned); not in the response
    # The check's own fit, at its inlier distance whatever the request's fitness_threshold: what answers
    # are judged and ranked by (a user's distance only changes what is reported). Not in the response.
    score: AlignmentScore
    stage: "Stage"  # which part of the pipeline gave the answer
    model: str  # whose network gave it (for `features`, the request's first network's)
    points: CloudReports
    refinement: RefineReport | None
    timings_ms: dict[str, float]  # queue, inference, preprocess, postprocess; batch_size

    @property
    def transform(self) -> np.ndarray:
        return to_matrix(self.rotation, self.translation)


class CloudSampler:
    """Brings one cloud to any point count, reproducible from (cloud, seed) alone.

    Farthest-point sampling of very large clouds first takes a seeded random subset of
    fps_max_input points: the result stays deterministic and the cost bounded. A larger count
    extends the farthest points of a smaller one (its first points are the smaller sample).
    """

    def __init__(self, points: np.ndarray, sampling: Sampling, seed: int, fps_max_input: int):
        rng = np.random.default_rng(seed)  # a fresh generator per cloud: the other cloud does not matter
        self.subset = None
        if sampling == "fps" and len(points) > fps_max_input:
            self.subset = np.sort(rng.choice(len(points), size=fps_max_input, replace=False))
        self.points = points if self.subset is None else points[self.subset]
        self.sampling, self.rng_state = sampling, rng.bit_generator.state
        self.farthest = FarthestPoints(self.points) if sampling == "fps" else None

    def indices(self, count: int) -> np.ndarray:
        rng = np.random.default_rng()
        rng.bit_generator.state = self.rng_state  # each count draws as if it came first
        found = resample_indices(len(self.points), count, self.sampling, rng, self.points, self.farthest)
        return found if self.subset is None else self.subset[found]


@dataclass(frozen=True)
class _Prepared:
    source: np.ndarray  # distinct source points, user units, without init
    target: np.ndarray
    source_network: np.ndarray  # [network_points, 3] float32, normalised, init applied
    target_network: np.ndarray
    normalisation: Normalisation
    init: np.ndarray  # 4x4
    points: CloudReports
    check: AlignmentClouds  # at most CHECK_MAX_POINTS of each cloud: what refinement and the check use
    coarse: AlignmentClouds  # at most COARSE_POINTS of each of those: the refinement's coarse pass
    scored: np.ndarray  # at most STARTS_SCORE_POINTS of the check's source: they rank coarse answers
    samplers: dict[str, CloudSampler]  # per cloud: another count extends this one's farthest points
    seconds: float


def _prepare(
    source: np.ndarray,
    target: np.ndarray,
    count: int,
    options: RegistrationOptions,
    settings: Settings,
    threads: int = 1,
    base: _Prepared | None = None,
) -> _Prepared:
    """The pair made ready for a network of `count` points, its check on `threads`; `base`, the same
    pair made ready for another count, lends its checked distinct points, its samplers and its
    check's clouds."""
    started = time.perf_counter()
    clouds, sampled, reports = {}, {}, {}
    samplers = {} if base is None else base.samplers
    for name, points in (("source", source), ("target", target)):
        if base is None:
            unique = check_cloud(points, name, settings.min_points, settings.max_cloud_points)
            samplers[name] = CloudSampler(unique, options.sampling, options.seed, settings.fps_max_input_points)
        else:
            unique = getattr(base, name)
        clouds[name], sampled[name] = unique, unique[samplers[name].indices(count)]
        reports[name] = CloudReport(len(points), len(points) - len(unique), count, len(unique) < count)
    init = np.eye(4) if options.init is None else options.init
    source_sampled = apply_transform(sampled["source"], *from_matrix(init))
    normalisation = Normalisation(source_sampled, sampled["target"])
    if base is None:  # the same for every point count: built once per request
        source_check, target_check = (subset(clouds[name], CHECK_MAX_POINTS) for name in ("source", "target"))
        check = AlignmentClouds(source_check, target_check, threads=threads)
        coarse = check
        if min(len(source_check), len(target_check)) > 2 * COARSE_POINTS:  # else it saves too little
            coarse = AlignmentClouds(
                subset(source_check, COARSE_POINTS), subset(target_check, COARSE_POINTS), check.spacing, threads
            )
        scored = subset(source_check, STARTS_SCORE_POINTS)
    else:
        check, coarse, scored = base.check, base.coarse, base.scored
    return _Prepared(
        source=clouds["source"],
        target=clouds["target"],
        source_network=normalisation.source(source_sampled).astype(np.float32),
        target_network=normalisation.target(sampled["target"]).astype(np.float32),
        normalisation=normalisation,
        init=init,
        points=CloudReports(**reports),
        check=check,
        coarse=coarse,
        scored=scored,
        samplers=samplers,
        seconds=time.perf_counter() - started,
    )


def _user_transform(prepared: _Prepared, prediction: Prediction, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The network's answer for the normalised source turned by `start`, in the user's units and
    composed with `init`: a transform of the user's source."""
    if not (np.isfinite(prediction.rotation).all() and np.isfinite(prediction.translation).all()):
        raise RegistrationFailed("the model returned a non-finite transform for these clouds")
    rotation = nearest_rotation(np.asarray(prediction.rotation, np.float64)) @ start
    rotation, translation = prepared.normalisation.to_user_units(
        rotation, np.asarray(prediction.translation, np.float64)
    )
    return from_matrix(to_matrix(rotation, translation) @ prepared.init)


@dataclass(frozen=True)
class _Candidate:
    rotation: np.ndarray
    translation: np.ndarray
    refinement: RefineReport | None
    verification: Verification


def refine_distances(spacing: float, scale: float, max_distance: float | None = None) -> list[float]:
    """The correspondence distances of one refinement, in the user's units: the user's own, else
    coarse to fine, first a share of the clouds' size (COARSE_DISTANCE_NORMALISED in the frame that
    `scale` normalises to, at most COARSE_MAX_SPACINGS point spacings) and then REFINE_SPACINGS
    point spacings."""
    if max_distance:
        return [max_distance]
    fine = REFINE_SPACINGS * spacing
    return [min(max(COARSE_DISTANCE_NORMALISED / scale, fine), COARSE_MAX_SPACINGS * spacing), fine]


def _checked(
    prepared: _Prepared,
    rotation: np.ndarray,
    translation: np.ndarray,
    refine_options,
    min_fitness: float = MIN_FITNESS,
    fine_bar: float = 0.0,
) -> _Candidate:
    """Refine (when asked) and check one answer (its fit at least `min_fitness` both ways). Without a
    distance of the user's, the refinement runs coarse to fine: first at a share of the clouds' size
    on fewer points (to pull in a few degrees' error), then at a few point spacings (to settle on
    the surfaces). Where the coarse pass ran on fewer points than the check's, the fine pass is
    skipped for an answer then matching under `fine_bar` of the scoring points at LOOSE_SPACINGS."""
    refinement = None
    if refine_options is not None:
        network_transform = to_matrix(rotation, translation)
        distances = refine_distances(prepared.check.spacing, prepared.normalisation.scale, refine_options.max_distance)
        iterations = 0
        for stage, distance in enumerate(distances, start=1):
            clouds = prepared.check if stage == len(distances) else prepared.coarse
            if (
                fine_bar > 0
                and stage > 1
                and prepared.coarse is not prepared.check
                and prepared.check.fitness(prepared.scored, rotation, translation, LOOSE_SPACINGS) < fine_bar
            ):
                break
            rotation, translation, steps = clouds.refine(
                rotation,
                translation,
                distance,
                max_iterations=refine_options.max_iterations,
                max_seconds=REFINE_MAX_SECONDS,
            )
            iterations += steps
            used = distance
        refinement = RefineReport(used, iterations, network_transform)
    return _Candidate(rotation, translation, refinement, prepared.check.verify(rotation, translation, min_fitness))


def _result(
    prepared: _Prepared,
    chosen: _Candidate,
    stage: Stage,
    model: str,
    options: RegistrationOptions,
    timings: dict[str, float],
) -> RegistrationResult:
    score = chosen.verification.score
    fitness, inlier_rmse, threshold = score.fitness, score.inlier_rmse, score.threshold
    if options.fitness_threshold is not None:  # the user's own inlier distance, on the full clouds
        threshold = options.fitness_threshold
        moved = apply_transform(prepared.source, chosen.rotation, chosen.translation)
        fitness, inlier_rmse = fitness_and_rmse(moved, prepared.target, threshold)
    return RegistrationResult(
        rotation=chosen.rotation,
        translation=chosen.translation,
        fitness=fitness,
        inlier_rmse=inlier_rmse,
        fitness_threshold=threshold,
        verified=chosen.verification.verified,
        reason=chosen.verification.reason,
        unpinned=chosen.verification.unpinned,
        score=score,
        stage=stage,
        model=model,
        points=prepared.points,
        refinement=chosen.refinement,
        timings_ms={"preprocess_ms": prepared.seconds * 1000.0, **timings},
    )


def _finish(
    prepared: _Prepared,
    prediction: Prediction,
    network: Network,
    options: RegistrationOptions,
    start: np.ndarray | None = None,
    fine_bar: float = 0.0,
) -> RegistrationResult:
    """The network's answer (for the source turned by `start`), refined if asked (always, for a
    draft's coarse answer), and checked; `fine_bar` as _checked's."""
    started = time.perf_counter()
    rotation, translation = _user_transform(prepared, prediction, np.eye(3) if start is None else start)
    refine_options = options.refine or (RefineOptions() if network.stage == "draft" else None)
    chosen = _checked(prepared, rotation, translation, refine_options, MIN_FITNESS, fine_bar)
    timings = _model_timings([prediction]) | {"postprocess_ms": (time.perf_counter() - started) * 1000.0}
    return _result(prepared, chosen, network.stage, network.model, options, timings)


@dataclass(frozen=True)
class _FeatureGuess:
    rotation: np.ndarray
    translation: np.ndarray
    seconds: float
    spacing: float  # the point spacing the matcher's voxel followed


def _feature_guess(
    prepared: _Prepared, match: FeatureMatch | None = None, points: int = 0, spacing: float | None = None
) -> _FeatureGuess:
    """Feature matching (KISS-Matcher, or `match` with feature_match's signature), whatever the
    rotation, on the check's clouds or, where they are subsets, on up to `points` of each cloud: a
    coarse answer. `spacing`: the thinned clouds' point spacing, where an earlier guess measured it."""
    started = time.perf_counter()
    check = prepared.check
    clouds, spacings = (check.source, check.target), FEATURE_VOXEL_SPACINGS
    if not _thinned(prepared):
        spacing = check.spacing
    else:
        if spacing is None:
            spacing = max(
                point_spacing(subset(cloud, FEATURE_SPACING_POINTS), threads=check.threads)
                for cloud in (prepared.source, prepared.target)
            )
        spacings = THINNED_FEATURE_SPACINGS
        if points:
            clouds = (subset(prepared.source, points), subset(prepared.target, points))
    rotation, translation = (match or feature_match)(*clouds, spacing, spacings)
    return _FeatureGuess(rotation, translation, time.perf_counter() - started, spacing)


def _thinned(prepared: _Prepared) -> bool:
    """The check runs on a subset of either cloud."""
    check = prepared.check
    return len(prepared.source) > len(check.source) or len(prepared.target) > len(check.target)


def _finish_features(
    prepared: _Prepared, guess: _FeatureGuess, model: str, options: RegistrationOptions
) -> RegistrationResult:
    """Feature matching's answer, refined and checked."""
    started = time.perf_counter()
    chosen = _checked(prepared, guess.rotation, guess.translation, options.refine or RefineOptions())
    postprocess_ms = (time.perf_counter() - started + guess.seconds) * 1000.0
    timings = {"queue_ms": 0.0, "inference_ms": 0.0, "batch_size": 0, "postprocess_ms": postprocess_ms}
    return _result(prepared, chosen, "features", model, options, timings)


def _starts(prepared: _Prepared) -> tuple[list[np.ndarray], np.ndarray]:
    """The starts' network inputs: the source turned by each start, and the target, each sampled
    down to STARTS_POINTS."""
    source, target = (at_most(cloud, STARTS_POINTS) for cloud in (prepared.source_network, prepared.target_network))
    return [source @ start.T.astype(np.float32) for start in STARTS], target


def _finish_multistart(
    prepared: _Prepared,
    predictions: list[Prediction],
    model: str,
    options: RegistrationOptions,
    settled: Sequence[RegistrationResult] = (),
    anyway: int = 0,
) -> tuple[list[RegistrationResult], dict[str, float]]:
    """The network's answers from the rotated starts, the best few by fitness each refined and
    checked (every one of them can contradict another), and what they cost. With verified answers
    to judge (`settled`), only their rivals are refined: none, where no start fits loosely as well."""
    started = time.perf_counter()
    pairs = zip(STARTS, predictions, strict=True)
    coarse = [_user_transform(prepared, prediction, start) for start, prediction in pairs]
    candidates = _rivals(prepared, coarse, options, settled, anyway)
    cost = _model_timings(predictions) | {"postprocess_ms": (time.perf_counter() - started) * 1000.0}
    return [_result(prepared, candidate, "multistart", model, options, _FREE) for candidate in candidates], cost


def _rivals(
    prepared: _Prepared,
    coarse: list[tuple[np.ndarray, np.ndarray]],
    options: RegistrationOptions,
    settled: Sequence[RegistrationResult],
    anyway: int = 0,
) -> list[_Candidate]:
    """The best few coarse answers by fitness (STARTS_REFINED, or `anyway` where more), each refined
    and checked. With verified answers to judge (`settled`), only their rivals (none, where no coarse
    answer fits loosely as well) and the best `anyway` of those far from them; without, those still
    far off after the coarse pass skip the fine one (FINE_PASS_MIN_FITNESS)."""
    check, scored = prepared.check, prepared.scored
    ranked = [(check.fitness(scored, *pose, INLIER_SPACINGS), *pose) for pose in coarse]
    ranked.sort(key=lambda entry: -entry[0])
    if settled:
        rival = _rival_test(prepared, settled)
        far = [entry for entry in ranked if _apart(entry[1], settled)]
        ranked = far[:anyway] + [entry for entry in far[anyway:] if rival(*entry[1:])]
    refine_options = options.refine or RefineOptions()  # coarse answers: every candidate is refined
    best = ranked[: max(STARTS_REFINED, anyway)]
    fine_bar = 0.0 if settled else FINE_PASS_MIN_FITNESS  # a rival skipped could leave a wrong answer verified
    return [
        _checked(prepared, rotation, translation, refine_options, MIN_STARTS_FITNESS, fine_bar)
        for _, rotation, translation in best
    ]


def _rival_test(
    prepared: _Prepared, settled: Sequence[RegistrationResult], share: float = RIVAL_LOOSE_SHARE
) -> Callable[[np.ndarray, np.ndarray], bool]:
    """Whether a coarse answer (R, t) may be a rival of the verified answers `settled`, worth refining to
    judge them: further than RIVAL_REACH_DEG from each (nearer ones settle on it), fitting at least
    `share` as well as the best of them at LOOSE_SPACINGS, on the pair's scoring points."""

    def loose(rotation: np.ndarray, translation: np.ndarray) -> float:
        return prepared.check.fitness(prepared.scored, rotation, translation, LOOSE_SPACINGS)

    bar = share * max(loose(answer.rotation, answer.translation) for answer in settled)

    def rival(rotation: np.ndarray, translation: np.ndarray) -> bool:
        return _apart(rotation, settled) and loose(rotation, translation) >= bar

    return rival


def _apart(rotation: np.ndarray, settled: Sequence[RegistrationResult]) -> bool:
    """Further than RIVAL_REACH_DEG from each of the answers `settled`: refined, it would not settle on them."""
    return bool(min(rotation_angle_deg(rotation, answer.rotation) for answer in settled) > RIVAL_REACH_DEG)


def _half_turns(
    prepared: _Prepared, answer: RegistrationResult, model: str, options: RegistrationOptions
) -> tuple[list[RegistrationResult], dict[str, float]]:
    """The answer turned half a turn about each principal axis of the target, where that fits
    loosely as well, refined and checked: the rivals of a flat or box-like shape's flipped pose,
    which feature matching and the network can both settle on. And what they cost."""
    started = time.perf_counter()
    axes = prepared.check.target_axes.T
    flips = [2.0 * np.outer(axis, axis) - np.eye(3) for axis in axes]  # half a turn about each axis
    candidates = _rivals(prepared, _turned_about_target(prepared, answer, flips), options, [answer])
    cost = {"postprocess_ms": (time.perf_counter() - started) * 1000.0} | _FREE_MODEL
    return [_result(prepared, candidate, "multistart", model, options, _FREE) for candidate in candidates], cost


def _polished(
    prepared: _Prepared, answer: RegistrationResult, options: RegistrationOptions
) -> tuple[list[RegistrationResult], dict[str, float]]:
    """The answer turned POLISH_DEG either way about each principal axis of the target, each refined
    and checked: where the answer sits in a local minimum, a turn towards the truth settles there (a
    jittered chair verified 28 degrees off, whose truth fits better and tighter). And what they cost."""
    started = time.perf_counter()
    axes = prepared.check.target_axes.T
    directions = np.array([sign * axis for axis in axes for sign in (1.0, -1.0)])  # either way about each
    turns = Rotation.from_rotvec(np.radians(POLISH_DEG) * directions).as_matrix()
    refine_options = options.refine or RefineOptions()
    candidates = [
        _checked(prepared, rotation, translation, refine_options, MIN_STARTS_FITNESS)
        for rotation, translation in _turned_about_target(prepared, answer, turns)
    ]
    cost = {"postprocess_ms": (time.perf_counter() - started) * 1000.0} | _FREE_MODEL
    return [_result(prepared, candidate, answer.stage, answer.model, options, _FREE) for candidate in candidates], cost


def _turned_about_target(
    prepared: _Prepared, answer: RegistrationResult, turns: Sequence[np.ndarray]
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The answer (R, t) followed by each of `turns` about the centre of the target's points."""
    centre = prepared.check.target_centre
    return [(turn @ answer.rotation, turn @ (answer.translation - centre) + centre) for turn in turns]


def _unless_slid(
    prepared: _Prepared, answer: RegistrationResult, options: RegistrationOptions, guess: _FeatureGuess | None
) -> RegistrationResult:
    """The answer, or, when it is verified and matches less than SLIDE_FITNESS of the source and of its
    surfaces, a pose beside it that fits clearly better and passes the check too, not verified: both
    pass, and where the scene repeats itself (shelves, a corridor) the better fitting one may be the
    wrong one. Not looked for where feature matching's `guess`, which the answer did not start from,
    lies within SLIDE_GUESS_SHARE and AGREEMENT_DEG of it. Charged with the time the search took."""
    if not answer.verified or answer.score.fitness >= SLIDE_FITNESS:
        return answer
    started = time.perf_counter()
    check = prepared.check
    pinned = guess is not None and answer.stage != "features" and _lands_on(prepared, guess, answer, SLIDE_GUESS_SHARE)
    if pinned or _matches_most(prepared, answer):
        answer.timings_ms["postprocess_ms"] += (time.perf_counter() - started) * 1000.0
        return answer
    small = AlignmentClouds(
        subset(check.source, SLIDE_POINTS), subset(check.target, SLIDE_POINTS), check.spacing, threads=check.threads
    )

    def fit(rotation: np.ndarray, translation: np.ndarray) -> float:
        return check.fitness(prepared.scored, rotation, translation, INLIER_SPACINGS)

    def returned(rotation: np.ndarray, translation: np.ndarray) -> bool:
        """Back beside the answer: the finer pass would settle it there, where it fits no better."""
        moved = check.centres_apart((rotation, translation), (answer.rotation, answer.translation))
        return moved <= SLIDE_RETURN_SHARE and rotation_angle_deg(rotation, answer.rotation) <= AGREEMENT_DEG

    distances = refine_distances(check.spacing, prepared.normalisation.scale)
    bar = (1.0 + SLIDE_MARGIN) * fit(answer.rotation, answer.translation)
    best = answer
    for translation in slides(answer.translation, check.target, SLIDE_SHARES, SLIDE_DIAGONAL_SHARES):
        rotation, translation, _ = small.refine(
            answer.rotation, translation, distances[0], max_iterations=SLIDE_ITERATIONS
        )
        if returned(rotation, translation):
            continue
        for distance in distances[1:]:
            rotation, translation, _ = small.refine(rotation, translation, distance, max_iterations=SLIDE_ITERATIONS)
        if fit(rotation, translation) <= bar:
            continue
        candidate = _checked(prepared, rotation, translation, options.refine or RefineOptions())
        fitness = candidate.verification.score.fitness
        if candidate.verification.verified and fitness > (1.0 + SLIDE_MARGIN) * best.score.fitness:
            best = _result(prepared, candidate, answer.stage, answer.model, options, dict(answer.timings_ms))
    best.timings_ms["postprocess_ms"] += (time.perf_counter() - started) * 1000.0
    if best is answer:
        return answer
    away = float(np.linalg.norm(best.translation - answer.translation)) / check.target_extent
    reason = f"ambiguous: a pose {away:.0%} of the extent away also passes the check (a repeating scene?)"
    return dataclasses.replace(best, verified=False, reason=reason)


def _matches_most(prepared: _Prepared, answer: RegistrationResult) -> bool:
    """The answer matches at least SLIDE_FITNESS of the source, or of its surfaces (outliers lower the
    fitness, not the overlap): little room is left for a pose beside it or turned from it to fit as well."""
    fitness = answer.score.fitness
    return (
        fitness >= SLIDE_FITNESS or prepared.check.surface_fitness(answer.rotation, answer.translation) >= SLIDE_FITNESS
    )


_FREE_MODEL = {"queue_ms": 0.0, "inference_ms": 0.0, "batch_size": 0}
_FREE = _FREE_MODEL | {"postprocess_ms": 0.0}  # the timings of a candidate whose cost is paid in its stage's


def _rank(answer: RegistrationResult) -> tuple[bool, float]:
    """Which answer to give: a verified one first, then the best fitting."""
    return answer.verified, answer.score.fitness


def _model_timings(predictions: list[Prediction]) -> dict[str, float]:
    return {
        "queue_ms": max(prediction.queue_ms for prediction in predictions),
        "inference_ms": sum(prediction.inference_ms for prediction in predictions),
        "batch_size": max(prediction.batch_size for prediction in predictions),
    }


async def register_clouds(
    source: np.ndarray,
    target: np.ndarray,
    options: RegistrationOptions,
    settings: Settings,
    networks: Sequence[Network],
    run_blocking: RunBlocking = asyncio.to_thread,
    threads: int = 1,
    match: FeatureMatch | None = None,
) -> RegistrationResult:
    """Register `source` onto `target` (both N x 3 in user units, already through `as_points`).

    `options.method` must be set (`resolve_options`). Each network's `predict` receives the two
    normalised float32 clouds [network_points, 3] and returns the transform between them.
    `options.method` picks the path: the first network (`ifnet`), the global search with the first
    network (`global`), or the networks in turn (the first one's draft before it) until an answer
    passes the check, or fails it only on its constraint matching most of the source (UNPINNED_FITNESS),
    and, when none does, the global search (`auto`). The CPU-heavy steps run
    through `run_blocking` (a worker thread by default) so that the event loop keeps serving;
    refinement and the check run on `threads`; feature matching runs `match` (in the service, in a
    child process: service.features), else feature_match in process. Raises InvalidInput for
    clouds that cannot be registered.
    """
    first = networks[0]
    count = (first.draft or first).network_points if options.method == "auto" else first.network_points
    base = await run_blocking(_prepare, source, target, count, options, settings, threads)
    answer, guess = await _answer(source, target, base, options, settings, networks, run_blocking, threads, match)
    return await run_blocking(_judged, base, answer, options, guess)


def _judged(
    prepared: _Prepared, answer: RegistrationResult, options: RegistrationOptions, guess: _FeatureGuess | None
) -> RegistrationResult:
    """The answer as a request gives it: past the slide check and, a network's, the second opinion of
    feature matching's `guess`."""
    return _unless_uncorroborated(_unless_slid(prepared, answer, options, guess), guess)


def _unless_uncorroborated(answer: RegistrationResult, guess: _FeatureGuess | None) -> RegistrationResult:
    """The answer, or, where it is a network's, verified, matching under UNCORROBORATED_MIN_FITNESS of
    the source, and feature matching's guess (if any) lies further than AGREEMENT_DEG from it, the
    same answer not verified."""
    if (
        not answer.verified
        or answer.stage not in ("ifnet", "draft")
        or answer.score.fitness >= UNCORROBORATED_MIN_FITNESS
        or (guess is not None and _confirms(guess, answer))
    ):
        return answer
    reason = (
        f"low overlap and no second opinion: it matches {answer.score.fitness:.2f} of the source "
        f"(at least {UNCORROBORATED_MIN_FITNESS:g} needed where feature matching does not agree)"
    )
    return dataclasses.replace(answer, verified=False, reason=reason)


def verdicts(
    source: np.ndarray, target: np.ndarray, poses: Sequence[tuple[np.ndarray, np.ndarray]], settings: Settings
) -> list[RegistrationResult]:
    """The verdict a request's answer gets, for each given pose (R, t) of `source` onto `target`:
    the check, then the slide check and feature matching's second opinion (_judged), as under
    `auto`, with feature matching's guess. For calibrating them on pairs with known truth."""
    options = RegistrationOptions()
    prepared = _prepare(source, target, STARTS_POINTS, options, settings)
    guess = _feature_guess(prepared)
    answers = (_result(prepared, _checked(prepared, *pose, None), "ifnet", "", options, dict(_FREE)) for pose in poses)
    return [_judged(prepared, answer, options, guess) for answer in answers]


async def _answer(
    source: np.ndarray,
    target: np.ndarray,
    base: _Prepared,
    options: RegistrationOptions,
    settings: Settings,
    networks: Sequence[Network],
    run_blocking: RunBlocking,
    threads: int,
    match: FeatureMatch | None,
) -> tuple[RegistrationResult, _FeatureGuess | None]:
    """register_clouds' answer before its slide check, from the pair made ready (`base`) for the
    first network asked, and feature matching's guess where it was made."""
    first = networks[0]
    auto = options.method == "auto"
    # The global path runs on the first clouds prepared: the check's clouds are the same for every count.
    prepared = {len(base.source_network): base}
    answers: list[RegistrationResult] = []
    discarded: list[dict[str, float]] = []  # the timings of stages that gave no candidate, but were paid for
    features: _FeatureGuess | None = None
    features_answer: RegistrationResult | None = None
    unconfirmed: list[RegistrationResult] = []

    async def ask(network: Network) -> RegistrationResult:
        count = network.network_points
        if count not in prepared:  # a model exported for another point count; the check's clouds are the same
            prepared[count] = await run_blocking(_prepare, source, target, count, options, settings, threads, base)
        prediction = await network.predict(prepared[count].source_network, prepared[count].target_network)
        # Under `auto` with nothing verified to judge, a network's answer is one more candidate of the search.
        fine_bar = FINE_PASS_MIN_FITNESS if auto and not unconfirmed else 0.0
        return await run_blocking(_finish, prepared[count], prediction, network, options, None, fine_bar)

    if options.method != "global":
        asked = networks if auto else networks[:1]
        if auto and first.draft is not None:
            # A draft's answer stands only where feature matching, an independent method, agrees; the
            # guess is needed on every path of `auto`, so it comes first. A request alone in its worker
            # (all `threads`) starts the draft's first call, which needs only the prepared clouds,
            # beside it; among others, that call would wait its turn in the queue first.
            first_call = None
            if threads > 1 and first.draft.start_beside is not None:
                first_call = await first.draft.start_beside(base.source_network, base.target_network)
            try:
                features = await run_blocking(_feature_guess, base, match)
            except BaseException:
                if first_call is not None:
                    first_call.cancel()
                raise
            draft, paid, features_answer, unconfirmed = await _confirmed_draft(
                base, features, first.draft, options, run_blocking, first_call
            )
            if draft is not None and draft.verified and (options.init is not None or _turned(draft.rotation, base)):
                # Asked from the user's guess or at feature matching's turn, either of which may be a
                # symmetric shape's flipped pose: its half turns judge it. Either may be any pose that
                # passes the check, and where it matches little of the source and of its surfaces (room
                # for a turn about another axis, not a principal one, to fit as well) the rotated starts
                # judge it too (docs/verification-stress.md; docs/training/experiments/README.md,
                # "8 EdgeConv neighbours").
                found, cost = await run_blocking(_half_turns, base, draft, first.model, options)
                started = time.perf_counter()
                most = await run_blocking(_matches_most, base, draft)
                costs = [cost, _FREE_MODEL | {"postprocess_ms": (time.perf_counter() - started) * 1000.0}]
                if not most:
                    rivals, cost = await _judged_by_starts(
                        base, first, [draft], options, run_blocking, STARTS_JUDGING_ANYWAY
                    )
                    found, costs = found + rivals, costs + [cost]
                answers = [draft, *found]
                await _polish(base, answers, costs, options, run_blocking)
                return _given_and_charged(answers, options.method, costs), features
            if draft is not None:
                return draft, features
            discarded += paid
            # Feature matching's answer before the models': they follow only where it fails the check and has
            # not settled unpinned.
            if features_answer is None:
                features_answer = await run_blocking(_finish_features, base, features, first.model, options)
            features, features_answer = await _matched_wider(
                base, features, features_answer, match, options, run_blocking, discarded
            )
            if features_answer.verified or _settled_unpinned(features_answer, base):
                asked = []
        for network in asked:
            answers.append(await ask(network))
            if answers[-1].verified or (auto and _settled_unpinned(answers[-1], base)):
                break
        answers += unconfirmed  # the draft's verified answers feature matching did not confirm: judged with the rest
        if options.method == "ifnet" and not answers[0].verified:
            return answers[0], features
    # Feature matching: the global path's cheapest stage, and a second opinion on a verified answer.
    features = features or await run_blocking(_feature_guess, base, match)
    settled = [answer for answer in answers if answer.verified]
    if features_answer is not None:  # refined and checked already, for the draft
        answers.append(features_answer)
    elif settled and _confirms(features, settled[0]):
        # It agrees with the verified answer: nothing to refine or judge. Its time still counts.
        settled[0].timings_ms["postprocess_ms"] += features.seconds * 1000.0
    else:
        answer = await run_blocking(_finish_features, base, features, first.model, options)
        if not settled and options.method != "ifnet":  # else a second opinion: only a search tries harder
            features, answer = await _matched_wider(base, features, answer, match, options, run_blocking, discarded)
        answers.append(answer)
    # The rotated starts search for an answer where none is verified and, past `ifnet`, judge the
    # verified ones: on a symmetric shape a network or feature matching may fit a flipped pose as
    # well as the right one. Under `auto` an unpinned answer matching most of the source ends the search,
    # and a start's unverified answer replaces an unpinned one only where it fits clearly better.
    if options.method != "ifnet":
        verified = [answer for answer in answers if answer.verified]
        if verified or not (auto and any(_settled_unpinned(answer, base) for answer in answers)):
            if auto and _thinned(base) and [a.stage for a in verified] == ["features"]:
                # A scan too large for the check whole: feature matching's answer alone is verified. Its half
                # turns judge a scene's flip at a fraction of the starts' cost (24 calls, refinements on
                # thousands of points), whose network answers on a scene land far from anything that fits.
                found, cost = await run_blocking(_half_turns, base, verified[0], first.model, options)
            else:
                anyway = STARTS_JUDGING_ANYWAY if _corroborated(verified, features) else UNCORROBORATED_JUDGING_ANYWAY
                found, cost = await _judged_by_starts(base, first, verified, options, run_blocking, anyway)
            answers += _fitting_clearly_better(found, answers) if auto and not verified else found
            discarded.append(cost)
            await _polish(base, answers, discarded, options, run_blocking)
    # `ifnet` answers with the network, whatever else fits; the other stages only judge it.
    return _given_and_charged(answers, options.method, discarded), features


async def _matched_wider(
    prepared: _Prepared,
    features: _FeatureGuess,
    answer: RegistrationResult,
    match: FeatureMatch | None,
    options: RegistrationOptions,
    run_blocking: RunBlocking,
    discarded: list[dict[str, float]],
) -> tuple[_FeatureGuess, RegistrationResult]:
    """Feature matching's guess and its `answer` or, where that fails the check on a thinned cloud
    (the matcher saw the check's subset) and has not settled unpinned (one that has, a second match
    never bettered; under `auto` the search ends there), the guess of a second match on up to
    WIDER_FEATURE_POINTS of each cloud and its answer, if verified, or unpinned where the first is
    not (it fits and settles, the first does not). The answer set aside goes to `discarded`."""
    settled = answer.verified or _settled_unpinned(answer, prepared)
    if settled or not _thinned(prepared) or WIDER_FEATURE_POINTS <= CHECK_MAX_POINTS:
        return features, answer
    wider = await run_blocking(_feature_guess, prepared, match, WIDER_FEATURE_POINTS, features.spacing)
    wider_answer = await run_blocking(_finish_features, prepared, wider, answer.model, options)
    if not (wider_answer.verified or (wider_answer.unpinned and not answer.unpinned)):
        discarded.append(wider_answer.timings_ms)
        return features, answer
    discarded.append(answer.timings_ms)
    return wider, wider_answer


def _fitting_clearly_better(
    candidates: list[RegistrationResult], answers: list[RegistrationResult]
) -> list[RegistrationResult]:
    """The candidates that may replace the unpinned `answers`: verified, or fitting RIVAL_FITNESS_MARGIN
    better than all of them (on a tabletop a flip of the scene fits about as well as the truth)."""
    fits = [answer.score.fitness for answer in answers if answer.unpinned]
    if not fits:
        return candidates
    bar = max(fits) + RIVAL_FITNESS_MARGIN
    return [answer for answer in candidates if answer.verified or answer.score.fitness >= bar]


async def _polish(
    prepared: _Prepared,
    answers: list[RegistrationResult],
    costs: list[dict[str, float]],
    options: RegistrationOptions,
    run_blocking: RunBlocking,
) -> None:
    """Where the best ranked answer is verified and of POLISHED_STAGES, add its polished answers
    (_polished) to `answers` and their cost to `costs`: judged with the others, a better one outranks it."""
    best = max(answers, key=_rank)
    if best.verified and best.stage in POLISHED_STAGES:
        found, cost = await run_blocking(_polished, prepared, best, options)
        answers += found
        costs.append(cost)


async def _judged_by_starts(
    prepared: _Prepared,
    network: Network,
    verified: list[RegistrationResult],
    options: RegistrationOptions,
    run_blocking: RunBlocking,
    anyway: int,
) -> tuple[list[RegistrationResult], dict[str, float]]:
    """The network's (its draft's, where it has one) answers from the rotated starts: candidates, or
    only the rivals of the `verified` answers they judge (_finish_multistart), and their cost."""
    starter = network.draft or network
    turned, target = await run_blocking(_starts, prepared)
    predictions = await asyncio.gather(*(starter.predict(cloud, target) for cloud in turned))
    return await run_blocking(_finish_multistart, prepared, list(predictions), network.model, options, verified, anyway)


async def _confirmed_draft(
    prepared: _Prepared,
    features: _FeatureGuess,
    draft: Network,
    options: RegistrationOptions,
    run_blocking: RunBlocking,
    first_call: "asyncio.Future[Prediction] | None",
) -> tuple[RegistrationResult | None, list[dict[str, float]], RegistrationResult | None, list[RegistrationResult]]:
    """The draft's answer where feature matching confirms it, else None and the timings of the
    draft's answers set aside (paid for, but no candidate); the guess refined and checked when that
    was needed, and the draft's verified answers set aside: candidates of the rest of the pipeline,
    which judges them with its own (an answer the guess does not confirm may still be right).

    The draft is asked for the source as it lies (`first_call`, where that call is under way
    already) and, unless that answer is verified, again for the source turned by the guess where
    that turn is beyond NETWORK_REACH_DEG: the network knows turns of up to 45 deg, the guess any
    turn. A verified answer is confirmed by the guess within AGREEMENT_DEG of it (where it matches
    at least UNCORROBORATED_MIN_FITNESS of the source) or, where the guess is too coarse for that (a
    few degrees off on noisy clouds), by the guess refined and checked. An answer from the guess
    lies near it by construction, so it stands only if the first answer, refined, does not
    contradict it (as the model's answer would in the second opinion; one set aside that fits
    loosely under CONTRADICTING_LOOSE_SHARE as well is not refined for that); where that answer is
    verified too, the pair is ambiguous (a symmetric shape) and the better fitting of them is the
    answer, not verified. A first answer that fails the check only on its constraint (unpinned: it
    fits and has settled, but the clouds would let it slide) stands unverified where the guess
    agrees with it in turn and translation, or refined is unpinned too and agrees with it: answers
    near it would fail alike, and one far from it would contradict both methods. An answer more than
    DRAFT_REACH_DEG from the guess is set aside unrefined: refinement would not bring the two within
    AGREEMENT_DEG."""
    paid: list[dict[str, float]] = []  # the timings of the draft's answers refined and checked
    unrefined: list[Prediction] = []  # the draft's answers set aside unrefined (too far from the guess)
    refined: list[RegistrationResult] = []  # the guess refined and checked, once needed
    finished: list[RegistrationResult] = []  # the draft's answers refined and checked

    async def ask(start: np.ndarray, call: Awaitable[Prediction] | None = None) -> tuple[Prediction, bool]:
        if call is None:
            call = draft.predict((prepared.source_network @ start.T).astype(np.float32), prepared.target_network)
        prediction = await call
        rotation = _user_transform(prepared, prediction, start)[0]
        near = rotation_angle_deg(rotation, features.rotation) <= DRAFT_REACH_DEG
        if not near:
            unrefined.append(prediction)
        return prediction, near

    async def finish(prediction: Prediction, start: np.ndarray, judging: bool = False) -> RegistrationResult:
        """The answer refined and checked: a candidate (which, far off after the coarse pass, skips the
        fine one) or, `judging` a verified answer, its rival (every pass: skipped, a right rival could
        leave a wrong answer verified)."""
        unrefined[:] = [other for other in unrefined if other is not prediction]
        fine_bar = 0.0 if judging else FINE_PASS_MIN_FITNESS
        answer = await run_blocking(_finish, prepared, prediction, draft, options, start, fine_bar)
        paid.append(answer.timings_ms)
        finished.append(answer)
        return answer

    async def confirmed(answer: RegistrationResult) -> bool:
        """Feature matching's guess agrees with the answer: as it is (an unpinned answer, which may
        have slid off the truth with its turn right, also in translation), or refined and judged
        alike (verified for a verified answer, unpinned for an unpinned one)."""
        if answer.verified:
            # At low overlap a local minimum a few degrees beside the truth passes the check, and a guess
            # beside the truth may lie within AGREEMENT_DEG of it: the guess refined must find it there.
            near = _confirms(features, answer) and answer.score.fitness >= UNCORROBORATED_MIN_FITNESS
        else:
            near = _lands_on(prepared, features, answer, UNPINNED_AGREEMENT_SHARE)
        if near:
            return True
        if not refined:
            refined.append(await run_blocking(_finish_features, prepared, features, draft.model, options))
        alike = refined[0].verified if answer.verified else refined[0].unpinned
        # Near in turn but fitting clearly better, the refined guess is not the answer's twin: the answer
        # sits in a local minimum beside it (a TUM room view: 3.7 deg and 0.49 m off at fitness 0.30, the
        # guess refined onto the truth at 0.50).
        better = answer.verified and refined[0].score.fitness >= answer.score.fitness + CONFIRMING_BETTER_FIT
        return alike and not better and rotation_angle_deg(refined[0].rotation, answer.rotation) <= AGREEMENT_DEG

    def unpaid() -> list[dict[str, float]]:
        """The timings of the draft's answers set aside unrefined: their calls still count."""
        return [_model_timings([prediction]) | {"postprocess_ms": 0.0} for prediction in unrefined]

    def stands(answer: RegistrationResult) -> tuple[RegistrationResult, list, None, list]:
        spent = paid + [other.timings_ms for other in refined] + unpaid()
        _charged(answer, [timings for timings in spent if timings is not answer.timings_ms])
        if not refined:  # the guess alone confirmed it: its time still counts
            answer.timings_ms["postprocess_ms"] += features.seconds * 1000.0
        return answer, [], None, []

    def set_aside() -> tuple[None, list, RegistrationResult | None, list[RegistrationResult]]:
        kept = [answer for answer in finished if answer.verified]
        spent = [timings for timings in paid if all(timings is not answer.timings_ms for answer in kept)]
        return None, spent + unpaid(), refined[0] if refined else None, kept

    own_prediction, near = await ask(np.eye(3), first_call)
    own = await finish(own_prediction, np.eye(3)) if near else None
    if own is not None and own.verified:
        return stands(own) if await confirmed(own) else set_aside()  # else the guess contradicts it
    if own is not None and own.unpinned and await confirmed(own):
        # Two methods agree on a pose the clouds cannot pin down: any answer near it would fail the
        # check the same way, and one far from it would contradict them both. It stands, not verified.
        return stands(own)
    if not _turned(features.rotation, prepared):
        # The first call already saw the source within the network's reach of the guess's turn (none at
        # all where feature matching found nothing): turned by the guess, the draft answers the same.
        return set_aside()
    start = features.rotation @ prepared.init[:3, :3].T  # the guess's turn of the network's source
    prediction, near = await ask(start)
    if not near:
        return set_aside()
    chosen = await finish(prediction, start)
    if not (chosen.verified and await confirmed(chosen)):
        return set_aside()
    if own is None:  # set aside far from the guess: refined, it may contradict the guess's answer
        may_contradict = _rival_test(prepared, [chosen], CONTRADICTING_LOOSE_SHARE)
        if not may_contradict(*_user_transform(prepared, own_prediction, np.eye(3))):
            return stands(chosen)
        own = await finish(own_prediction, np.eye(3), judging=True)
    if _unless_contradicted(chosen, [chosen, own]).verified:
        return stands(chosen)
    if own.verified:  # two verified answers apart: the clouds fit both, whatever else is asked
        candidates = [chosen, own, *refined]
        return stands(_unless_contradicted(max(candidates, key=_rank), candidates))
    return set_aside()


def _settled_unpinned(answer: RegistrationResult, prepared: _Prepared) -> bool:
    """The answer fails the check only on its constraint and matches at least UNPINNED_FITNESS of the
    source (UNPINNED_FITNESS_THINNED on a thinned scan): under `auto` the search (the next models, the
    rotated starts) ends there."""
    bar = UNPINNED_FITNESS_THINNED if _thinned(prepared) else UNPINNED_FITNESS
    return answer.unpinned and answer.score.fitness >= bar


def _turned(rotation: np.ndarray, prepared: _Prepared) -> bool:
    """The rotation (an answer's, a guess's) lies beyond the network's reach (NETWORK_REACH_DEG) of the
    request's `init`."""
    return bool(rotation_angle_deg(rotation, prepared.init[:3, :3]) > NETWORK_REACH_DEG)


def _given(answers: list[RegistrationResult], method: str) -> RegistrationResult:
    """The answer a request gets: under `ifnet` the network's, else the best ranked, judged by the
    others (_unless_contradicted). A contradicted answer leaves nothing verified, so (past `ifnet`)
    the best fitting answer is given, flagged alike."""
    best = answers[0] if method == "ifnet" else max(answers, key=_rank)
    judged = _unless_contradicted(best, answers)
    if best.verified and not judged.verified and method != "ifnet":
        fittest = max(answers, key=lambda answer: answer.score.fitness)
        judged = dataclasses.replace(fittest, verified=False, reason=judged.reason)
    return judged


def _given_and_charged(
    answers: list[RegistrationResult], method: str, discarded: list[dict[str, float]]
) -> RegistrationResult:
    """The answer given (_given), charged with every stage that ran: the other answers' and the
    `discarded` timings (stages that gave no candidate)."""
    given = _given(answers, method)
    others = [answer.timings_ms for answer in answers if answer.timings_ms is not given.timings_ms]
    return _charged(given, others + discarded)


def _charged(answer: RegistrationResult, others: list[dict[str, float]]) -> RegistrationResult:
    """The answer with the cost of the other stages that ran for it."""
    for timings in others:
        for name in ("inference_ms", "postprocess_ms"):
            answer.timings_ms[name] += timings[name]
        for name in ("queue_ms", "batch_size"):  # the longest wait, the largest batch
            answer.timings_ms[name] = max(answer.timings_ms[name], timings[name])
    return answer


def _confirms(guess: _FeatureGuess, answer: RegistrationResult) -> bool:
    """Feature matching's guess lies within AGREEMENT_DEG of the answer (the caller judges the answer)."""
    return rotation_angle_deg(answer.rotation, guess.rotation) <= AGREEMENT_DEG


def _corroborated(verified: list[RegistrationResult], guess: _FeatureGuess) -> bool:
    """Feature matching vouches for one of the `verified` answers (all of a request's): its guess lies
    within AGREEMENT_DEG of it (_confirms), or it is feature matching's own answer, refined."""
    return any(answer.stage == "features" or _confirms(guess, answer) for answer in verified)


def _lands_on(prepared: _Prepared, guess: _FeatureGuess, answer: RegistrationResult, share: float) -> bool:
    """The guess agrees with the answer in turn (_confirms) and puts the source's centre within `share`
    of the extent of where the answer puts it."""
    pose, guessed = (answer.rotation, answer.translation), (guess.rotation, guess.translation)
    return _confirms(guess, answer) and prepared.check.centres_apart(pose, guessed) <= share


def _tighter(answer: RegistrationResult, other: RegistrationResult) -> bool:
    """`answer` fits at least as well as `other`, its inliers much nearer the surface: those of a right
    answer lie within the sampling gap and the noise, those of a wrong pose anywhere within the
    inlier distance (measured in service/README.md, "POST /register")."""
    ours, theirs = answer.score, other.score
    return ours.fitness >= theirs.fitness and ours.inlier_rmse < RIVAL_RMSE_SHARE * theirs.inlier_rmse


def _unless_contradicted(best: RegistrationResult, answers: list[RegistrationResult]) -> RegistrationResult:
    """A verified answer that another answer contradicts is not verified when the other is verified
    too (unless the answer is much tighter: _tighter) or fits about as well (it may have failed the
    check only by sliding, as on a near-symmetric shape): both fit, so the clouds (a symmetric
    object, a repetitive scene) do not tell which is right."""
    if not best.verified:
        return best
    rivals = [
        other
        for other in answers
        if (other.verified and not _tighter(best, other))
        or other.score.fitness >= best.score.fitness - RIVAL_FITNESS_MARGIN
    ]
    apart = max(float(rotation_angle_deg(best.rotation, other.rotation)) for other in rivals)
    if apart <= AGREEMENT_DEG:
        return best
    reason = f"ambiguous: another answer {apart:.0f} degrees away fits as well (a symmetric shape?)"
    return dataclasses.replace(best, verified=False, reason=reason)


# ---------------------------------------------------------------- a request's pairs


def resolve_options(options: RegistrationOptions, service: ServiceState) -> tuple[RegistrationOptions, list[Network]]:
    """The options with the method filled in, and the networks the request may ask, in order: the
    model it names (or the default and, under `auto`, the others after it), each checked against
    the request's point count."""
    method = options.method or service.settings.default_method
    first = service.model(options.model)
    models = [first]
    if method == "auto" and options.model is None:
        models += [model for model in service.models.values() if model is not first]
    limit, count = service.settings.max_network_points, options.network_points
    if count is not None and count > limit:
        raise InvalidInput("network_points", f"is {count}, more than this service's limit of {limit}")
    networks = []
    for model in models:
        info = model.info
        fewest = info.min_network_points
        if count is not None and count < fewest:
            raise InvalidInput(
                "network_points", f"is {count}; model {info.name!r} needs at least {fewest} points per cloud"
            )
        # No wait limit of the batcher's own: the request's deadline bounds the whole request, and
        # cancelling it drops the pair from the queue.
        draft = None
        if model.draft is not None:
            draft_points = count or model.draft.engine.info.network_points
            draft = Network(info.name, draft_points, model.draft.submit, "draft", start_beside=model.draft.start_beside)
        networks.append(Network(info.name, count or info.network_points, model.batcher.submit, draft=draft))
    return options.model_copy(update={"method": method}), networks


async def register_pairs(
    service: ServiceState, request: Request, pairs: list[tuple[np.ndarray, np.ndarray]], options: RegistrationOptions
) -> list[RegistrationResult]:
    """Run pairs through the registration pipeline and the models' batchers, concurrently.

    With several pairs, errors name the pair (`source[1]`). All pairs are dropped from the
    queue if the client disconnects while they wait.
    """
    options, networks = resolve_options(options, service)
    settings = service.settings
    # small_gicp's threads, as a model call's: all of them for a request alone in its worker.
    threads = settings.threads if service.in_flight <= 1 and len(pairs) == 1 else 1
    room = settings.max_queue_size
    if len(pairs) > room:  # could never be queued at once, however long the client waited
        raise InvalidInput(
            "source", f"holds {len(pairs)} pairs, more than this service queues at once; send at most {room}"
        )

    async def one(index: int, source: np.ndarray, target: np.ndarray) -> RegistrationResult:
        try:
            result = await register_clouds(
                source, target, options, settings, networks, threads=threads, match=service.feature_match
            )
        except InvalidInput as error:
            if len(pairs) == 1:
                raise
            raise InvalidInput(f"{error.field}[{index}]", error.problem) from None
        service.metrics.answers.labels(result.model, result.stage, str(result.verified).lower()).inc()
        return result

    async def all_pairs() -> list[RegistrationResult]:
        tasks = [asyncio.ensure_future(one(index, *pair)) for index, pair in enumerate(pairs)]
        try:
            return list(await asyncio.gather(*tasks))
        except BaseException:
            for task in tasks:
                task.cancel()
            raise

    return await cancel_on_disconnect(request, all_pairs())


@asynccontextmanager
async def request_deadline(settings: Settings) -> AsyncIterator[None]:
    """Bounds a whole request (reading, parsing, preprocessing, queue, inference) by the timeout.

    Raises RequestTimeoutError (504). Work already handed to a thread (parsing a large file,
    sampling) runs to its end, but the client gets its answer on time and the pair leaves the
    batcher's queue.
    """
    timeout = settings.request_timeout_s
    try:
        async with asyncio.timeout(timeout):
            yield
    except TimeoutError:
        raise RequestTimeoutError(
            f"no answer within the request timeout of {timeout:g} s; retry later or send fewer points"
        ) from None


async def _disconnected(request: Request) -> None:
    """Returns when the client closes the connection (the body must have been read already)."""
    while (await request.receive())["type"] != "http.disconnect":
        pass


async def cancel_on_disconnect(request: Request, work: Awaitable[T]) -> T:
    """Await `work`, cancelling it (and raising ClientDisconnected) if the client goes away first."""
    work_task = asyncio.ensure_future(work)
    watcher = asyncio.ensure_future(_disconnected(request))
    try:
        done, _ = await asyncio.wait({work_task, watcher}, return_when=asyncio.FIRST_COMPLETED)
    except asyncio.CancelledError:  # the request's deadline, or the server stopping
        work_task.cancel()
        watcher.cancel()
        await asyncio.wait({work_task})  # its pair leaves the batcher's queue before the answer goes out
        raise
    watcher.cancel()
    if work_task in done:
        return work_task.result()
    work_task.cancel()
    await asyncio.wait({work_task})  # let it unwind: its pair leaves the batcher's queue
    raise ClientDisconnected("the client disconnected before its registration finished")
