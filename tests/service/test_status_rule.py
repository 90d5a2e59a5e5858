"""The status rule of service/README.md, one request of each kind: 400 unreadable, 408 too slow,
413 too large, 415 encoding, 422 invalid content, 429 full, and 5xx only for the service's own
failures (500 a fault, 504 its own slowness)."""

import asyncio
import gzip

import numpy as np
import pytest

from service.engine import OnnxEngine
from service.settings import Settings

pytestmark = pytest.mark.anyio

SOURCE = np.random.default_rng(9).normal(size=(100, 3))
PAIR = {"source": SOURCE.tolist(), "target": (SOURCE + 0.2).tolist()}
JSON = {"Content-Type": "application/json"}


class FailingEngine:
    """The service's own fault: the model call raises."""

    def __init__(self, engine):
        self.engine = engine
        self.info = engine.info
        self.failing = False

    def run(self, source, target, beside=False):
        if self.failing:
            raise RuntimeError("model session broke")
        return self.engine.run(source, target)


async def test_one_request_of_each_kind_gets_its_status(serve, tiny_model, gated_engine):
    gated = gated_engine(FailingEngine(OnnxEngine(tiny_model, 1)), gated=False)
    settings = Settings(model_path=tiny_model, max_body_bytes=64 * 1024, request_timeout_s=1.0, max_in_flight=1)
    statuses = {}
    async with serve(settings, engines=[gated]) as (app, client):

        async def slow_body():
            yield b'{"source": '
            await asyncio.sleep(3)
            yield b"[]}"

        statuses["unreadable"] = await client.post(
            "/register", content=b"not gzip at all", headers={**JSON, "Content-Encoding": "gzip"}
        )
        statuses["too slow"] = await client.post("/register", content=slow_body(), headers=JSON)
        statuses["too large"] = await client.post("/register", content=b" " * 100_000, headers=JSON)
        statuses["encoding"] = await client.post(
            "/register", content=gzip.compress(b"{}"), headers={**JSON, "Content-Encoding": "br"}
        )
        statuses["invalid content"] = await client.post("/register", json={**PAIR, "source": [[0, 0, 0]] * 3})
        statuses["file format"] = await client.post("/register", files={"source": b"x y z", "target": b"x y z"})

        gated.gate.clear()  # one request holds the only slot
        gated.entered.clear()  # set by the warm-up's model calls
        held = asyncio.ensure_future(client.post("/register", json=PAIR))
        await asyncio.to_thread(gated.entered.wait, 10)
        statuses["full"] = await client.post("/register", json=PAIR)
        statuses["own slowness"] = await held
        gated.gate.set()

        gated.engine.failing = True
        statuses["own fault"] = await client.post("/register", json=PAIR)
        gated.engine.failing = False
        statuses["fine"] = await client.post("/register", json=PAIR)

    expected = {
        "unreadable": 400,
        "too slow": 408,
        "too large": 413,
        "encoding": 415,
        "invalid content": 422,
        "file format": 415,
        "full": 429,
        "own slowness": 504,
        "own fault": 500,
        "fine": 200,
    }
    assert {kind: answer.status_code for kind, answer in statuses.items()} == expected
    for kind, answer in statuses.items():
        if kind != "fine":  # every refusal says what is wrong
            assert answer.json()["detail"], kind
    assert "Retry-After" in statuses["full"].headers
