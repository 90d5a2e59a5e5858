"""Request and response schemas of every route (pydantic), with the examples shown in the OpenAPI docs."""

from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    AliasChoices,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    PlainSerializer,
    PlainValidator,
    ValidationInfo,
    WithJsonSchema,
    computed_field,
    field_validator,
)
from pydantic_core import PydanticCustomError

from service.validation import InvalidInput, as_points, as_rigid_transform

Sampling = Literal["fps", "random"]
Method = Literal["auto", "ifnet", "global"]


def _example_pair() -> tuple[list[list[float]], list[list[float]], list[list[float]]]:
    """A small table (48 points: a top and two legs of different sizes) and the same table turned 30
    degrees about z and shifted. No symmetry, so the transform is unique (tests/service/test_accuracy.py
    registers it with the shipped model)."""
    rng = np.random.default_rng(0)
    top, long_leg, short_leg = (  # boxes as (centre, half-size)
        ((0.0, 0.0, 0.0), (1.0, 0.6, 0.1)),
        ((0.4, 0.25, 0.5), (0.15, 0.1, 0.5)),
        ((-0.4, -0.2, 0.3), (0.1, 0.1, 0.3)),
    )
    source = np.array(
        [np.add(centre, rng.uniform(-1.0, 1.0, 3) * half) for centre, half in [top, long_leg, short_leg] * 16]
    )
    turn = np.radians(30.0)
    rotation = np.array([[np.cos(turn), -np.sin(turn), 0.0], [np.sin(turn), np.cos(turn), 0.0], [0.0, 0.0, 1.0]])
    translation = np.array([0.2, -0.1, 0.05])
    source = np.round(source, 4)
    target = source @ rotation.T + translation
    transform = np.eye(4)
    transform[:3, :3], transform[:3, 3] = rotation, translation
    return source.tolist(), np.round(target, 4).tolist(), np.round(transform, 4).tolist()


EXAMPLE_SOURCE, EXAMPLE_TARGET, EXAMPLE_TRANSFORM = _example_pair()
# The shipped network's own answer to the first request example, rounded: /v2/models/object/infer's
# (tests/service/test_accuracy.py). /register's default answer, refined, is the example's motion itself.
EXAMPLE_ANSWER = [
    [0.8653, -0.5013, -0.0037, 0.2046],
    [0.5012, 0.8653, -0.0053, -0.0911],
    [0.0059, 0.0027, 1.0, 0.05],
    [0.0, 0.0, 0.0, 1.0],
]
IDENTITY = np.eye(4).tolist()


def _validate_points(value: Any, info: ValidationInfo) -> np.ndarray:
    try:
        return as_points(value, info.field_name or "points")
    except InvalidInput as error:
        raise PydanticCustomError("points", error.problem) from None


def _validate_init(value: Any, info: ValidationInfo) -> np.ndarray:
    try:
        return as_rigid_transform(value, info.field_name or "init")
    except InvalidInput as error:
        raise PydanticCustomError("rigid_transform", error.problem) from None


def _matrix_schema(rows: int, columns: int) -> dict:
    row = {"type": "array", "items": {"type": "number"}, "minItems": columns, "maxItems": columns}
    return {"type": "array", "items": row, "minItems": rows, "maxItems": rows}


_to_list = PlainSerializer(lambda array: np.asarray(array).tolist(), return_type=list)

Points = Annotated[
    np.ndarray,
    PlainValidator(_validate_points),
    _to_list,
    WithJsonSchema(
        {
            "type": "array",
            "items": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
            "description": "Points as [x, y, z] in your units; finite numbers only.",
        }
    ),
]
RigidMatrix = Annotated[np.ndarray, PlainValidator(_validate_init), _to_list, WithJsonSchema(_matrix_schema(4, 4))]
_from_array = BeforeValidator(lambda value: value.tolist() if isinstance(value, np.ndarray) else value)
Matrix3 = Annotated[list[list[float]], _from_array, Field(min_length=3, max_length=3)]
Matrix4 = Annotated[list[list[float]], _from_array, Field(min_length=4, max_length=4)]
Vector3 = Annotated[list[float], _from_array, Field(min_length=3, max_length=3)]


# ---------------------------------------------------------------- /register


class RefineOptions(BaseModel):
    """ICP refinement on the full-resolution clouds after the network."""

    model_config = ConfigDict(extra="forbid")

    max_distance: float | None = Field(
        None,
        gt=0,
        strict=True,  # true/false are not distances
        allow_inf_nan=False,
        description="Largest point-pair distance ICP uses, in your units. Default: 0.05 in the normalised frame "
        "(5% of the radius of the larger resampled cloud), converted to your units.",
    )
    max_iterations: int = Field(30, ge=1, le=500, strict=True, description="Most ICP iterations.")


class RegistrationOptions(BaseModel):
    """Everything about a registration except the clouds (also the `options` part of binary uploads)."""

    model_config = ConfigDict(extra="forbid", arbitrary_types_allowed=True)

    init: RigidMatrix | None = Field(
        None, description="Initial guess (rigid 4x4, your units), applied to the source before the network."
    )
    refine: RefineOptions | None = Field(
        None, description="Refine with ICP: `true` for the defaults, or an object with its parameters."
    )
    network_points: int | None = Field(
        None,
        ge=8,
        strict=True,
        validation_alias=AliasChoices("network_points", "max_points"),
        description="Points per cloud given to the network (default: the model's own count). Larger clouds are "
        "subsampled to it, smaller ones upsampled by repeating points. `max_points` is accepted as an older name.",
    )
    model: str | None = Field(
        None,
        min_length=1,
        max_length=200,
        description="The model whose network runs, by name (`GET /v2/models` lists them). Default: `object` (or the "
        "one model served), and with `method` `auto` the other models' networks in turn where an answer fails the "
        "check, before the search.",
    )
    method: Method | None = Field(
        None,
        description="`ifnet`: the network's answer, checked. `global`: a search that handles any rotation (feature "
        "matching, then the network from 24 rotated starts), checked. `auto`: the network (its draft first, refined, "
        "kept where feature matching agrees), and the search when no answer passes the check. Default: the service's "
        "`IFNET_DEFAULT_METHOD` (`auto` unless set).",
    )
    sampling: Sampling = Field(
        "fps", description="Subsampling: deterministic farthest-point (`fps`) or seeded random (`random`)."
    )
    seed: int = Field(0, ge=0, le=2**32 - 1, strict=True, description="Seed of random sampling and upsampling.")
    fitness_threshold: float | None = Field(
        None,
        gt=0,
        strict=True,
        allow_inf_nan=False,
        description="Inlier distance of the reported `fitness` and `inlier_rmse`, your units (default 1.5 point "
        "spacings); the check and the choice of answer keep their own.",
    )

    @field_validator("refine", mode="before")
    @classmethod
    def _refine_flag(cls, value: Any) -> Any:
        """`true` means ICP with its defaults, `false` none; anything else must be the options object."""
        if value is True:
            return {}
        if value is False:
            return None
        return value


class RegisterRequest(RegistrationOptions):
    """Two point clouds in the same units; the answer moves `source` onto `target`."""

    source: Points = Field(description="The cloud to move, as a list of [x, y, z].")
    target: Points = Field(description="The cloud to align to, as a list of [x, y, z].")

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {"source": EXAMPLE_SOURCE, "target": EXAMPLE_TARGET},
                {
                    "source": EXAMPLE_SOURCE,
                    "target": EXAMPLE_TARGET,
                    "init": IDENTITY,
                    "refine": {"max_iterations": 50},
                },
            ]
        }
    )


class PointCounts(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    received: int = Field(description="Points in the request.")
    duplicates_removed: int = Field(description="Exact duplicates dropped before resampling.")
    network_points: int = Field(description="Points the network saw.")
    upsampled: bool = Field(description="True when the distinct points were fewer and some were repeated.")


class CloudPointCounts(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    source: PointCounts
    target: PointCounts


class Refinement(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    max_distance: float = Field(description="ICP's correspondence distance, your units.")
    iterations: int
    network_transform: Matrix4 = Field(description="The transform before refinement.")


class DraftDescription(BaseModel):
    version: str = Field(description="First 12 hex digits of the draft's weights' (or file's) SHA-256.")
    network_points: int = Field(description="Points per cloud the draft is given.")
    blocks: int | None = Field(description="Feedback Registration Blocks it unrolls (the model: 9).")


class ModelDescription(BaseModel):
    model_config = ConfigDict(protected_namespaces=(), from_attributes=True)

    name: str = Field(description="The model's name in the repository (its file's name without `.onnx`).")
    version: str = Field(description="First 12 hex digits of the weights' (or model file's) SHA-256.")
    weights_sha256: str | None = None
    file_sha256: str
    preset: str | None = None
    network_points: int = Field(description="Points per cloud the network was exported for (the default).")
    draft: DraftDescription | None = Field(
        None,
        description="The model's draft network, which `method` `auto` asks before it: the same weights over fewer "
        "blocks and points, whose coarser answer is always refined.",
    )

    @computed_field(description="The older name of `network_points`.", json_schema_extra={"deprecated": True})
    @property
    def native_num_points(self) -> int:
        return self.network_points


class Timings(BaseModel):
    model_config = ConfigDict(from_attributes=True)

    read_ms: float = Field(0.0, description="Receiving and parsing the body (JSON, files or arrays).")
    queue_ms: float = Field(description="Wait in the batcher's queue.")
    inference_ms: float = Field(description="Model calls (each shared by its whole batch).")
    preprocess_ms: float = Field(description="Checks, duplicate removal, sampling and normalisation.")
    postprocess_ms: float = Field(description="Mapping back, refinement, the check and the global path's matching.")
    total_ms: float = Field(
        description="The whole request. Under `auto` the draft's first call may run beside feature matching, "
        "so the parts may add up to more."
    )
    batch_size: int = Field(description="Pairs in the model call that served this one.")


class RegisterResponse(BaseModel):
    """The rigid transform with target ~ source @ rotation^T + translation, like Open3D's RegistrationResult."""

    model_config = ConfigDict(
        protected_namespaces=(),
        json_schema_extra={
            "examples": [
                {
                    "rotation": [row[:3] for row in EXAMPLE_TRANSFORM[:3]],
                    "translation": [row[3] for row in EXAMPLE_TRANSFORM[:3]],
                    "transform": EXAMPLE_TRANSFORM,
                    "fitness": 1.0,
                    "inlier_rmse": 0.00004,
                    "fitness_threshold": 0.1548,
                    "verified": True,
                    "reason": None,
                    "stage": "draft",
                    "points": {
                        "source": {"received": 48, "duplicates_removed": 0, "network_points": 384, "upsampled": True},
                        "target": {"received": 48, "duplicates_removed": 0, "network_points": 384, "upsampled": True},
                    },
                    "refinement": {
                        "max_distance": 0.2065,
                        "iterations": 3,
                        "network_transform": [
                            [0.8567, -0.5157, 0.0082, 0.1908],
                            [0.5153, 0.8564, 0.0319, -0.1162],
                            [-0.0235, -0.0231, 0.9995, 0.0521],
                            [0.0, 0.0, 0.0, 1.0],
                        ],
                    },
                    "model": {
                        "name": "object",
                        "version": "ca91aa32a6d4",
                        "weights_sha256": "ca91aa32a6d47a70244a359ce08fb45dbb45fb80c0d2126a7149bdf37078f76c",
                        "file_sha256": "a50a0e58ddcabf7935ff71c8d5a853735eba4d304129312aea2a5794eeb23e52",
                        "preset": "fast",
                        "network_points": 768,
                        "draft": {"version": "ca91aa32a6d4", "network_points": 384, "blocks": 1},
                    },
                    "timings_ms": {
                        "read_ms": 0.6,
                        "queue_ms": 0.1,
                        "inference_ms": 12.4,
                        "preprocess_ms": 2.2,
                        "postprocess_ms": 6.3,
                        "total_ms": 20.0,
                        "batch_size": 1,
                    },
                }
            ]
        },
    )

    rotation: Matrix3
    translation: Vector3
    transform: Matrix4 = Field(description="[[rotation, translation], [0, 0, 0, 1]].")
    fitness: float = Field(description="Share of moved source points with a target point within fitness_threshold.")
    inlier_rmse: float = Field(description="RMS distance of those inlier pairs, your units.")
    fitness_threshold: float = Field(
        description="The inlier distance: 1.5 point spacings of the clouds unless the request set its own."
    )
    verified: bool = Field(
        description="The answer passed the check: enough overlap both ways, the matching points pin the motion down, "
        "and a refinement does not move it. False means do not trust it; `reason` says why."
    )
    reason: str | None = Field(None, description="Why the answer is not verified.")
    stage: Literal["ifnet", "draft", "multistart", "features"] = Field(
        description="What produced the answer: the network, the model's draft network (refined), the network from a "
        "rotated start (or another answer turned half a turn about the target's principal axes, refined), or feature "
        "matching."
    )
    points: CloudPointCounts
    refinement: Refinement | None = Field(
        description="The refinement the answer went through; null for a network's answer without `refine` (the "
        "draft's, the rotated starts' and feature matching's coarse answers are always refined)."
    )
    model: ModelDescription = Field(
        description="The model whose network gave the answer; for `features`, the request's model (named or default)."
    )
    timings_ms: Timings

    @classmethod
    def from_result(cls, result: Any, model: ModelDescription, read_ms: float, total_ms: float) -> "RegisterResponse":
        """The answer from the pipeline's result, whose attributes carry the response's names."""
        fields = {name: getattr(result, name) for name in cls.model_fields if hasattr(result, name)}
        timings = {**result.timings_ms, "read_ms": read_ms, "total_ms": total_ms}
        return cls.model_validate({**fields, "model": model, "timings_ms": timings})


class FieldError(BaseModel):
    field: str
    problem: str


class ErrorResponse(BaseModel):
    detail: str = Field(description="What is wrong and, where it helps, what to do.")
    errors: list[FieldError] = Field(default_factory=list)

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "detail": "source: has 3 points; at least 32 distinct points are needed",
                    "errors": [{"field": "source", "problem": "has 3 points; at least 32 distinct points are needed"}],
                }
            ]
        }
    )


# ---------------------------------------------------------------- health and readiness


class LatencySummary(BaseModel):
    count: int = Field(description="Successful /register requests in the window.")
    p50_ms: float | None
    p95_ms: float | None
    p99_ms: float | None


class ModelHealth(BaseModel):
    name: str
    version: str
    ready: bool = Field(description="Loaded and warmed up (the service's models are ready all or none).")
    queue_depth: int = Field(description="Pairs waiting for this model.")


class HealthResponse(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "status": "ok",
                    "ready": True,
                    "uptime_s": 3600.5,
                    "queue_depth": 0,
                    "in_flight": 1,
                    "latency": {"count": 1000, "p50_ms": 95.1, "p95_ms": 180.4, "p99_ms": 260.0},
                    "models": [{"name": "object", "version": "ca91aa32a6d4", "ready": True, "queue_depth": 0}],
                }
            ]
        }
    )

    status: Literal["ok", "failed"] = Field(
        "ok", description="`failed` (with HTTP 503) once the model's warm-up has failed: restart the process."
    )
    detail: str | None = Field(None, description="What failed, when status is `failed`.")
    ready: bool
    uptime_s: float
    queue_depth: int = Field(description="Pairs waiting for a model, all models together.")
    in_flight: int = Field(description="Registration requests admitted and not yet answered (at most max_in_flight).")
    latency: LatencySummary
    models: list[ModelHealth] = Field(description="Each served model (empty until they are loaded).")


class ReadyResponse(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={"examples": [{"ready": True, "detail": "models loaded and warmed up: object"}]}
    )

    ready: bool
    detail: str


# ---------------------------------------------------------------- Open Inference Protocol v2


class V2Tensor(BaseModel):
    name: str
    shape: list[int]
    datatype: str
    data: list[Any] = Field(description="Row-major values, flat or nested.")
    parameters: dict[str, Any] | None = None


class V2RequestedOutput(BaseModel):
    name: str
    parameters: dict[str, Any] | None = None


class V2InferRequest(BaseModel):
    """`source` [B, N, 3] and `target` [B, M, 3] FP32 (or [N, 3] for one pair), in your units."""

    id: str | None = None
    parameters: dict[str, Any] | None = Field(
        None, description="Optional `network_points`, `sampling` and `seed`, as in /register."
    )
    inputs: list[V2Tensor]
    outputs: list[V2RequestedOutput] | None = None

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "id": "pair-1",
                    "inputs": [
                        {
                            "name": "source",
                            "shape": [1, len(EXAMPLE_SOURCE), 3],
                            "datatype": "FP32",
                            "data": [value for point in EXAMPLE_SOURCE for value in point],
                        },
                        {
                            "name": "target",
                            "shape": [1, len(EXAMPLE_TARGET), 3],
                            "datatype": "FP32",
                            "data": [value for point in EXAMPLE_TARGET for value in point],
                        },
                    ],
                }
            ]
        }
    )


class V2InferResponse(BaseModel):
    model_config = ConfigDict(
        protected_namespaces=(),
        json_schema_extra={
            "examples": [
                {
                    "model_name": "object",
                    "model_version": "ca91aa32a6d4",
                    "id": "pair-1",
                    "outputs": [
                        {
                            "name": "rotation",
                            "shape": [1, 3, 3],
                            "datatype": "FP32",
                            "data": [v for row in EXAMPLE_ANSWER[:3] for v in row[:3]],
                        },
                        {
                            "name": "translation",
                            "shape": [1, 3],
                            "datatype": "FP32",
                            "data": [row[3] for row in EXAMPLE_ANSWER[:3]],
                        },
                    ],
                }
            ]
        },
    )

    model_name: str
    model_version: str
    id: str | None = None
    outputs: list[V2Tensor]


class V2TensorMetadata(BaseModel):
    name: str
    datatype: str
    shape: list[int]


class V2ModelMetadata(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "name": "object",
                    "versions": ["3f2a9c01d4e5"],
                    "platform": "onnxruntime_onnx",
                    "inputs": [
                        {"name": "source", "datatype": "FP32", "shape": [-1, -1, 3]},
                        {"name": "target", "datatype": "FP32", "shape": [-1, -1, 3]},
                    ],
                    "outputs": [
                        {"name": "rotation", "datatype": "FP32", "shape": [-1, 3, 3]},
                        {"name": "translation", "datatype": "FP32", "shape": [-1, 3]},
                    ],
                }
            ]
        }
    )

    name: str
    versions: list[str]
    platform: str
    inputs: list[V2TensorMetadata]
    outputs: list[V2TensorMetadata]
    parameters: dict[str, Any] = Field(default_factory=dict)


class V2ModelSummary(BaseModel):
    name: str
    version: str
    ready: bool


class V2ModelList(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={"examples": [{"models": [{"name": "object", "version": "ca91aa32a6d4", "ready": True}]}]}
    )

    models: list[V2ModelSummary]


class V2ServerMetadata(BaseModel):
    model_config = ConfigDict(
        json_schema_extra={"examples": [{"name": "ifnet-serve", "version": "0.1.0", "extensions": []}]}
    )

    name: str
    version: str
    extensions: list[str]


class V2Live(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{"live": True}]})

    live: bool


class V2Ready(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{"ready": True}]})

    ready: bool


class V2Error(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{"error": "source: shape [1, 10, 2] is not [B, N, 3]"}]})

    error: str
