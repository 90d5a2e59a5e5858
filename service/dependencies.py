"""FastAPI dependencies: the shared service state (models, settings), admission control and the
API key check."""

import secrets
from collections.abc import AsyncIterator
from typing import Annotated

from fastapi import Depends, Header, HTTPException, Request

from service.state import ServiceState


# Dependencies that never block are `async def`: FastAPI runs a plain `def` one on its thread pool,
# a hand-over per dependency and request.
async def get_service(request: Request) -> ServiceState:
    return request.app.state.service


async def get_loaded_service(service: Annotated[ServiceState, Depends(get_service)]) -> ServiceState:
    """The service once its models are loaded (requests queue during warm-up and run after it)."""
    if not service.models:
        raise HTTPException(503, "the models are not loaded yet; retry shortly", headers={"Retry-After": "1"})
    return service


async def admit(service: Annotated[ServiceState, Depends(get_loaded_service)]) -> AsyncIterator[ServiceState]:
    """Admits a registration request before its body is read, or answers 429 when
    `max_in_flight` requests are already being read, parsed, queued or run."""
    limit = service.settings.max_in_flight
    if service.in_flight >= limit:
        retry_after_s = max(model.batcher.retry_after_s() for model in service.models.values())
        raise HTTPException(
            429,
            f"the service is busy: {limit} registration requests are already in progress; "
            "retry after the Retry-After header's seconds",
            headers={"Retry-After": str(retry_after_s)},
        )
    service.in_flight += 1
    try:
        yield service
    finally:
        service.in_flight -= 1


async def require_api_key(
    service: Annotated[ServiceState, Depends(get_service)],
    x_api_key: Annotated[str | None, Header(description="The API key, if the service requires one.")] = None,
    authorization: Annotated[str | None, Header(description="Alternatively `Bearer <API key>`.")] = None,
) -> None:
    expected = service.settings.api_key
    if expected is None:
        return
    given = x_api_key
    if given is None and authorization and authorization.lower().startswith("bearer "):
        given = authorization[7:].strip()
    if given is None or not secrets.compare_digest(given.encode(), expected.get_secret_value().encode()):
        raise HTTPException(
            401,
            "missing or wrong API key: send it in the X-API-Key header (or Authorization: Bearer <key>)",
            headers={"WWW-Authenticate": "Bearer"},
        )


Service = Annotated[ServiceState, Depends(get_service)]
LoadedService = Annotated[ServiceState, Depends(get_loaded_service)]
# Ends before the response is sent, so a client that sends its next request on receiving an
# answer is not refused for a slot its last request still held.
AdmittedService = Annotated[ServiceState, Depends(admit, scope="function")]
