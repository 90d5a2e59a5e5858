"""Open Inference Protocol (KServe v2) routes, sharing /register's pipeline and batchers.

Every model of the repository is a v2 model. It takes clouds in the user's units, like /register:
`source` [B, N, 3] and `target` [B, M, 3] FP32 (or [N, 3] for one pair), and answers `rotation`
[B, 3, 3] and `translation` [B, 3] FP32. Each pair is deduplicated, resampled and normalised
exactly as /register does. `GET /v2/models` lists the models, as Triton's repository index does.
"""

import math
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Depends, HTTPException, Path, Request
from fastapi.responses import JSONResponse
from pydantic import ValidationError

from service import __version__
from service.dependencies import AdmittedService, LoadedService, Service, require_api_key
from service.registration import register_pairs, request_deadline
from service.schemas import (
    RegistrationOptions,
    V2Error,
    V2InferRequest,
    V2InferResponse,
    V2Live,
    V2ModelList,
    V2ModelMetadata,
    V2ModelSummary,
    V2Ready,
    V2ServerMetadata,
    V2Tensor,
    V2TensorMetadata,
)
from service.state import ServedModel, ServiceState
from service.uploads import parse_json
from service.validation import InvalidInput, as_points, invalid_request

router = APIRouter(prefix="/v2", tags=["open inference protocol v2"])

INPUTS = [V2TensorMetadata(name=name, datatype="FP32", shape=[-1, -1, 3]) for name in ("source", "target")]
OUTPUTS = [
    V2TensorMetadata(name="rotation", datatype="FP32", shape=[-1, 3, 3]),
    V2TensorMetadata(name="translation", datatype="FP32", shape=[-1, 3]),
]
_ERRORS = {status: {"model": V2Error} for status in (400, 401, 404, 413, 422, 429, 503, 504)}

ModelName = Annotated[
    str, Path(description="A served model's name (`GET /v2/models` lists them).", examples=["object"])
]


def _served(model_name: str, service: ServiceState) -> ServedModel:
    if model_name not in service.models:
        raise HTTPException(404, f"model {model_name!r} is not served here; this server serves {list(service.models)}")
    return service.models[model_name]


@router.get("", response_model=V2ServerMetadata, summary="Server metadata")
async def server_metadata() -> V2ServerMetadata:
    return V2ServerMetadata(name="ifnet-serve", version=__version__, extensions=[])


@router.get("/health/live", response_model=V2Live, summary="Server liveness")
async def live() -> V2Live:
    return V2Live(live=True)


@router.get("/health/ready", response_model=V2Ready, responses={503: {"model": V2Ready}}, summary="Server readiness")
async def server_ready(service: Service) -> JSONResponse:
    is_ready = service.ready.is_set()
    return JSONResponse(V2Ready(ready=is_ready).model_dump(), status_code=200 if is_ready else 503)


@router.get("/models", response_model=V2ModelList, responses={503: {"model": V2Error}}, summary="Models")
async def models(service: LoadedService) -> V2ModelList:
    """Every served model: its name, version and readiness (the models are ready all or none)."""
    is_ready = service.ready.is_set()
    return V2ModelList(
        models=[
            V2ModelSummary(name=name, version=model.info.version, ready=is_ready)
            for name, model in service.models.items()
        ]
    )


@router.get(
    "/models/{model_name}/ready",
    response_model=V2Ready,
    responses={404: {"model": V2Error}, 503: {"model": V2Ready}},
    summary="Model readiness",
)
async def model_ready(model_name: ModelName, service: LoadedService) -> JSONResponse:
    _served(model_name, service)
    return await server_ready(service)


@router.get("/models/{model_name}", response_model=V2ModelMetadata, responses=_ERRORS, summary="Model metadata")
async def model_metadata(model_name: ModelName, service: LoadedService) -> V2ModelMetadata:
    served = _served(model_name, service)
    info, draft = served.info, served.description().draft
    return V2ModelMetadata(
        name=info.name,
        versions=[info.version],
        platform="onnxruntime_onnx",
        inputs=INPUTS,
        outputs=OUTPUTS,
        parameters={
            "network_points": info.network_points,
            "preset": info.preset,
            "weights_sha256": info.weights_sha256,
            "file_sha256": info.file_sha256,
            "draft": None if draft is None else draft.model_dump(),
            "units": "inputs and translation in the caller's units; clouds are normalised server-side",
        },
    )


def _clouds(tensor: V2Tensor) -> np.ndarray:
    """[B, N, 3] float64 from a v2 FP32 tensor ([N, 3] counts as one pair)."""
    name = tensor.name
    if tensor.datatype != "FP32":
        raise InvalidInput(name, f"datatype must be FP32, got {tensor.datatype}")
    shape = tensor.shape
    if len(shape) not in (2, 3) or shape[-1] != 3 or any(size < 1 for size in shape):
        raise InvalidInput(name, f"shape must be [B, N, 3] or [N, 3], got {shape}")
    values = _flat_numbers(tensor.data, name)
    needed = math.prod(shape)  # Python integers: a huge shape cannot wrap around to a small product
    if len(values) != needed:
        raise InvalidInput(name, f"data has {len(values)} values but shape {shape} needs {needed}")
    try:
        data = np.asarray(values, dtype=np.float64)
    except OverflowError:  # an integer beyond float64's range
        raise InvalidInput(name, "data holds a number beyond the float range") from None
    clouds = data.reshape(shape if len(shape) == 3 else [1, *shape])
    for index, cloud in enumerate(clouds):  # finite and in range, as /register checks its clouds
        as_points(cloud, name if len(clouds) == 1 else f"{name}[{index}]")
    return clouds


def _flat_numbers(data: list, name: str) -> list:
    """The tensor's values, flattened row-major: JSON numbers only (numpy would read "1" or true as numbers)."""
    values = []
    pending = [iter(data)]
    while pending:
        for value in pending[-1]:
            if isinstance(value, list):
                pending.append(iter(value))
                break
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise InvalidInput(name, f"data must be JSON numbers (flat or nested row-major), got {value!r:.40}")
            values.append(value)
        else:
            pending.pop()
    return values


@router.post(
    "/models/{model_name}/infer",
    response_model=V2InferResponse,
    responses=_ERRORS,
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {"application/json": {"schema": {"$ref": "#/components/schemas/V2InferRequest"}}},
        }
    },
    dependencies=[Depends(require_api_key)],  # checked before the body is read
    summary="Register point clouds (v2 inference)",
)
async def infer(model_name: ModelName, request: Request, service: AdmittedService) -> V2InferResponse:
    """That model's network, through the same pipeline and batcher as /register; `parameters` may set
    the options of /register (`network_points`, `sampling`, `seed`, ...)."""
    model = _served(model_name, service)
    async with request_deadline(service.settings):
        return await _infer(await parse_json(request, V2InferRequest), request, service, model)


async def _infer(
    payload: V2InferRequest, request: Request, service: ServiceState, model: ServedModel
) -> V2InferResponse:
    tensors = {tensor.name: tensor for tensor in payload.inputs}
    for name in ("source", "target"):
        if name not in tensors:
            raise InvalidInput(name, f"missing input tensor (got {sorted(tensors)})")
    unknown = sorted(set(tensors) - {"source", "target"})
    if unknown:
        raise InvalidInput(unknown[0], "unknown input tensor; the inputs are `source` and `target`")
    for requested in payload.outputs or []:
        if requested.name not in ("rotation", "translation"):
            raise InvalidInput("outputs", f"unknown output {requested.name!r}; the outputs are rotation, translation")
    source, target = _clouds(tensors["source"]), _clouds(tensors["target"])
    if len(source) != len(target):
        raise InvalidInput("target", f"batch size {len(target)} differs from the source's {len(source)}")
    try:
        options = RegistrationOptions.model_validate(payload.parameters or {})
    except ValidationError as error:
        raise invalid_request(error, "parameters") from None
    if options.model not in (None, model.info.name):
        raise InvalidInput("model", f"is {options.model!r} in the parameters but {model.info.name!r} in the path")
    options = options.model_copy(update={"model": model.info.name})
    results = await register_pairs(service, request, list(zip(source, target, strict=True)), options)
    wanted = [requested.name for requested in payload.outputs] if payload.outputs else ["rotation", "translation"]
    values = {
        "rotation": np.stack([result.rotation for result in results]).astype(np.float32),
        "translation": np.stack([result.translation for result in results]).astype(np.float32),
    }
    return V2InferResponse(
        model_name=model.info.name,
        model_version=model.info.version,
        id=payload.id,
        outputs=[
            V2Tensor(name=name, shape=list(values[name].shape), datatype="FP32", data=values[name].ravel().tolist())
            for name in wanted
        ],
    )
