"""Property tests of the preprocessing in service/registration.py and model/geometry.py.

1. Round trip: for any cloud and any rigid motion, a model that solves the normalised pair
   exactly gives back the motion in the user's units: through `Normalisation` alone to float64
   rounding, and through the whole `register_clouds` pipeline (deduplication, resampling, the
   `init` guess, float32 network input) to float32 rounding.
2. Junk: whatever arrives (any nesting, dtype, shape or value), the input checks raise only
   `InvalidInput` (or pydantic's ValidationError for the options model), never anything else,
   and whatever they accept reaches the model finite, centred and within the network's radius.
"""

import asyncio

import numpy as np
import pytest
from conftest import kabsch, pipeline_inputs
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from pydantic import ValidationError

from model.geometry import Normalisation, apply_transform, rotation_angle_deg, to_matrix
from service.batcher import Prediction
from service.registration import register_clouds
from service.schemas import RegistrationOptions
from service.validation import InvalidInput, as_points, as_rigid_transform

PROPERTY_SETTINGS = settings(
    max_examples=150, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow]
)


def rotation_from_quaternion(q: np.ndarray) -> np.ndarray:
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def network_radius() -> float:
    """The radius `Normalisation` scales the larger cloud to (a constant, whatever the input)."""
    reference = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, -3.0, 0.0]])
    normalisation = Normalisation(reference, reference)
    return float(np.linalg.norm(normalisation.source(reference), axis=1).max())


RADIUS = network_radius()


quaternions = hnp.arrays(np.float64, 4, elements=st.floats(-1, 1)).filter(lambda q: np.linalg.norm(q) > 0.1)


@st.composite
def motions(draw) -> dict:
    """A random non-degenerate cloud in some units, somewhere, and a random rigid motion of it."""
    seed = draw(st.integers(0, 2**32 - 1))
    count = draw(st.integers(40, 400))
    units = 10.0 ** draw(st.integers(-3, 5))  # millimetres of a part .. kilometres of a city
    rng = np.random.default_rng(seed)
    shape = rng.normal(size=(count, 3)) * rng.uniform(0.2, 1.0, size=3)  # anisotropic blob
    offset = rng.normal(size=3) * draw(st.sampled_from([0.0, 1.0, 100.0]))
    source = (shape + offset) * units
    rotation = rotation_from_quaternion(draw(quaternions))
    translation = rng.normal(size=3) * units * draw(st.sampled_from([0.0, 0.1, 10.0]))
    return {"source": source, "rotation": rotation, "translation": translation, "units": units, "seed": seed}


def size_of(case: dict) -> float:
    """The scale the errors are relative to: cloud radius, distance from the origin, translation."""
    source = case["source"]
    return max(np.abs(source).max(), np.linalg.norm(case["translation"]), case["units"])


@PROPERTY_SETTINGS
@given(case=motions())
def test_normalise_denormalise_round_trip_recovers_any_rigid_motion(case):
    source, rotation, translation = case["source"], case["rotation"], case["translation"]
    target = apply_transform(source, rotation, translation)
    normalisation = Normalisation(source, target)
    source_n, target_n = normalisation.source(source), normalisation.target(target)
    for cloud in (source_n, target_n):  # the network's input contract: centred, one common scale
        assert np.abs(cloud.mean(axis=0)).max() < 1e-12 * RADIUS
    largest = max(np.linalg.norm(source_n, axis=1).max(), np.linalg.norm(target_n, axis=1).max())
    assert np.isclose(largest, RADIUS, rtol=1e-12)  # whatever the units and position

    recovered_rotation, recovered_translation = normalisation.to_user_units(*kabsch(source_n, target_n))
    assert rotation_angle_deg(recovered_rotation, rotation) < 1e-9
    np.testing.assert_allclose(recovered_translation, translation, rtol=0, atol=1e-11 * size_of(case))
    # And the recovered transform maps the user's source onto the user's target.
    moved = apply_transform(source, recovered_rotation, recovered_translation)
    np.testing.assert_allclose(moved, target, rtol=0, atol=1e-11 * size_of(case))


@PROPERTY_SETTINGS
@given(
    case=motions(),
    init_rotation=quaternions,
    init_shift=st.floats(-2, 2),
    network_points=st.sampled_from([32, 64, 256, 768]),
    duplicates=st.integers(0, 30),
    sampling=st.sampled_from(["random", "fps"]),
)
def test_the_whole_pipeline_recovers_any_rigid_motion(
    case, init_rotation, init_shift, network_points, duplicates, sampling
):
    """register_clouds with an exact model: dedupe, resample, init, float32 and back."""
    source, rotation, translation = case["source"], case["rotation"], case["translation"]
    source = np.concatenate([source, source[:duplicates]])  # exact duplicates, removed and counted
    target = apply_transform(source, rotation, translation)
    init = to_matrix(rotation_from_quaternion(init_rotation), np.full(3, init_shift * case["units"]))
    seen = []

    async def exact_model(source_n: np.ndarray, target_n: np.ndarray) -> Prediction:
        assert source_n.dtype == target_n.dtype == np.float32
        assert source_n.shape == target_n.shape == (network_points, 3)
        seen.append(1)
        return Prediction(*kabsch(source_n.astype(np.float64), target_n.astype(np.float64)))

    params = pipeline_inputs(network_points, exact_model, sampling=sampling, seed=case["seed"] % 1000, init=init)
    result = asyncio.run(register_clouds(source, target, *params, run_blocking=_run_inline))

    assert seen == [1]
    # float32 network input: about 1e-7 relative per coordinate, amplified a little by the fit.
    assert rotation_angle_deg(result.rotation, rotation) < 1e-3
    np.testing.assert_allclose(result.translation, translation, rtol=0, atol=2e-5 * size_of(case))
    assert result.points.source.received == len(source) and result.points.source.duplicates_removed >= duplicates
    assert result.fitness == 1.0


async def _run_inline(function, *args):
    return function(*args)


# ---------------------------------------------------------------- junk


scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(10**30), max_value=10**30),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=4),
    st.binary(max_size=4),
    st.complex_numbers(max_magnitude=1e3),
)
junk = st.recursive(
    scalars,
    lambda children: st.one_of(
        st.lists(children, max_size=6), st.tuples(children, children), st.dictionaries(st.text(max_size=3), children)
    ),
    max_leaves=30,
)
junk_arrays = hnp.arrays(
    dtype=st.one_of(
        hnp.integer_dtypes(),
        hnp.floating_dtypes(),
        hnp.boolean_dtypes(),
        hnp.complex_number_dtypes(),
        hnp.unicode_string_dtypes(max_len=3),
        hnp.datetime64_dtypes(),
    ),
    shape=hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=8),
)
float_clouds = hnp.arrays(
    np.float64,
    st.tuples(st.integers(0, 80), st.just(3)),
    elements=st.one_of(
        st.floats(-1e13, 1e13),
        st.sampled_from([0.0, 1.0, -1.0, 1e-300, 5e-324, 1e12, -1e12, np.nan, np.inf]),
    ),
)


def structured_clouds() -> st.SearchStrategy:
    """Valid-looking clouds that are degenerate in some way: few points, flat, thin, duplicated."""

    @st.composite
    def build(draw) -> np.ndarray:
        rng = np.random.default_rng(draw(st.integers(0, 2**16)))
        count = draw(st.integers(1, 120))
        extents = np.array([draw(st.sampled_from([0.0, 1e-9, 1e-5, 1e-3, 1.0, 1e6])) for _ in range(3)])
        cloud = rng.normal(size=(count, 3)) * extents + draw(st.sampled_from([0.0, 1.0, 1e9]))
        repeats = draw(st.integers(1, 4))
        return np.repeat(cloud, repeats, axis=0)

    return build()


@settings(max_examples=300, deadline=None, derandomize=True)
@given(value=st.one_of(junk, junk_arrays, float_clouds))
def test_junk_clouds_raise_only_invalid_input(value):
    try:
        points = as_points(value, "source")
    except InvalidInput as error:
        assert error.field == "source" and error.problem
        return
    assert points.dtype == np.float64 and points.ndim == 2 and points.shape[1] == 3
    assert np.isfinite(points).all()


@pytest.mark.filterwarnings("ignore:Casting complex values")  # numpy arrays only; JSON has no complex numbers
@settings(max_examples=200, deadline=None, derandomize=True)
@given(value=st.one_of(junk, junk_arrays, hnp.arrays(np.float64, (4, 4), elements=st.floats(allow_nan=True))))
def test_junk_init_matrices_raise_only_invalid_input(value):
    try:
        matrix = as_rigid_transform(value)
    except InvalidInput as error:
        assert error.field == "init" and error.problem
        return
    np.testing.assert_allclose(matrix[:3, :3] @ matrix[:3, :3].T, np.eye(3), atol=1e-9)
    assert np.linalg.det(matrix[:3, :3]) > 0 and np.array_equal(matrix[3], [0, 0, 0, 1])


@settings(max_examples=300, deadline=None, derandomize=True)
@given(options=st.one_of(junk, st.dictionaries(st.sampled_from(list(RegistrationOptions.model_fields)), junk)))
def test_junk_options_raise_only_validation_errors(options):
    try:
        RegistrationOptions.model_validate(options)
    except ValidationError as error:
        assert error.errors()


@settings(max_examples=200, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(
    source=st.one_of(float_clouds, structured_clouds()),
    target=st.one_of(float_clouds, structured_clouds()),
    network_points=st.sampled_from([8, 64]),
)
def test_accepted_clouds_reach_the_model_normalised_and_junk_is_invalid_input(source, target, network_points):
    """Whatever passes the checks reaches the model finite, centred and within the network's radius."""

    async def contract_checking_model(source_n: np.ndarray, target_n: np.ndarray) -> Prediction:
        for cloud in (source_n, target_n):
            assert cloud.shape == (network_points, 3) and cloud.dtype == np.float32
            assert np.isfinite(cloud).all()
            assert np.abs(cloud.mean(axis=0)).max() < 1e-3 * RADIUS
            assert np.linalg.norm(cloud, axis=1).max() <= RADIUS * (1.0 + 1e-5)
        return Prediction(np.eye(3), np.zeros(3))

    params = pipeline_inputs(network_points, contract_checking_model, min_points=8)
    try:
        clouds = as_points(source, "source"), as_points(target, "target")
        result = asyncio.run(register_clouds(*clouds, *params, run_blocking=_run_inline))
    except InvalidInput as error:
        assert error.field in ("source", "target") and error.problem
        return
    assert np.isfinite(result.transform).all()
    assert 0.0 <= result.fitness <= 1.0 and np.isfinite(result.inlier_rmse)


@pytest.mark.parametrize("count", [8, 9, 40])
def test_the_smallest_accepted_cloud_registers(count):
    """A deterministic anchor for the junk test: at min_points, a plain cloud is accepted."""
    cloud = np.random.default_rng(count).normal(size=(count, 3))

    async def identity(source_n, target_n):
        return Prediction(np.eye(3), np.zeros(3))

    params = pipeline_inputs(64, identity, min_points=8)
    result = asyncio.run(register_clouds(cloud, cloud, *params, run_blocking=_run_inline))
    assert result.fitness == 1.0 and result.points.source.upsampled
