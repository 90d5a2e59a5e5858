"""The micro-batcher: batching under load, one-at-a-time equivalence, backpressure (429), timeouts
(504), disconnects, failures and shutdown.

Engines are wrapped in a gate (see conftest.GatedEngine) so that tests decide when a model call
may proceed: queue states are then reached deterministically, without sleeping or timing.
"""

import asyncio
import json
import threading
import time

import numpy as np
import pytest
from conftest import pipeline_inputs, vanishing_request
from prometheus_client.parser import text_string_to_metric_families

from service.batcher import (
    InferenceError,
    MicroBatcher,
    Prediction,
    QueueFullError,
    RequestTimeoutError,
    ShuttingDownError,
)
from service.engine import OnnxEngine
from service.registration import register_clouds
from service.schemas import RegisterRequest
from service.settings import Settings

pytestmark = pytest.mark.anyio


def settings_for(model, **overrides) -> Settings:
    # One model call at a time, so that the pairs queued behind a running call form the next batch.
    return Settings(**{"model_path": model, "warmup": False, "max_batch_size": 8, "model_calls": 1, **overrides})


def pair(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    source = rng.normal(size=(80, 3)) * rng.uniform(0.5, 3.0)
    angle = rng.uniform(0, np.pi)
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    return source, source[rng.permutation(80)[:70]] @ rotation.T + rng.normal(size=3)


def payload(seed: int) -> dict:
    source, target = pair(seed)
    return {"source": source.tolist(), "target": target.tolist()}


async def wait_until(condition, what: str) -> None:
    """Yield to the event loop until condition() holds (a hang guard, not a timing assertion)."""
    for _ in range(6_000):
        if condition():
            return
        await asyncio.sleep(0.005)
    raise AssertionError(f"never reached: {what}")


def metric_samples(text: str) -> dict[str, float]:
    samples = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            labels = ",".join(f"{key}={value}" for key, value in sorted(sample.labels.items()))
            samples[f"{sample.name}{{{labels}}}"] = sample.value
    return samples


async def test_32_concurrent_requests_are_batched_and_each_gets_its_own_answer(serve, tiny_model, gated_engine):
    engine = gated_engine(OnnxEngine(tiny_model))
    async with serve(settings_for(tiny_model, max_queue_size=64, max_in_flight=32), engines=[engine]) as (app, client):
        batcher = app.state.service.models["object"].batcher
        requests = [asyncio.ensure_future(client.post("/register", json=payload(seed))) for seed in range(32)]
        # The first batch holds the worker at the gate; all other pairs queue up behind it.
        await wait_until(lambda: engine.at_gate + batcher.queue_depth == 32, "every pair at the gate or queued")
        engine.gate.set()
        responses = await asyncio.gather(*requests)
        metrics = metric_samples((await client.get("/metrics")).text)

    # One-at-a-time reference: the same pipeline, each pair alone in its own model call.
    async def alone(source, target):
        rotation, translation = engine.engine.run(source[None], target[None])
        return Prediction(rotation[0].astype(np.float64), translation[0].astype(np.float64))

    for seed, response in enumerate(responses):
        assert response.status_code == 200, response.text
        reference = await register_clouds(*pair(seed), *pipeline_inputs(64, alone))
        np.testing.assert_allclose(response.json()["transform"], reference.transform, rtol=1e-12, atol=1e-12)
    assert sum(engine.calls) == 32 and max(engine.calls) == 8
    assert metrics["ifnet_batch_size_count{model=object}"] == len(engine.calls)
    batches = metrics["ifnet_batch_size_count{model=object}"]
    assert metrics["ifnet_batch_size_bucket{le=1.0,model=object}"] < batches  # batches of > 1
    assert metrics["ifnet_batch_size_sum{model=object}"] == 32
    assert sorted(response.json()["timings_ms"]["batch_size"] for response in responses)[-8:] == [8] * 8


async def test_batched_results_equal_one_at_a_time_on_the_shipped_model(shipped_model, gated_engine):
    """The real network: pairs run in one batch give the same transforms as pairs run alone."""
    engine = gated_engine(OnnxEngine(shipped_model))
    batcher = MicroBatcher(engine, max_batch_size=4, max_queue_size=8)
    batcher.start()
    rng = np.random.default_rng(0)
    clouds = [
        (rng.normal(size=(64, 3)).astype(np.float32), rng.normal(size=(64, 3)).astype(np.float32)) for _ in range(4)
    ]
    blocker = asyncio.ensure_future(batcher.submit(*clouds[0]))
    await wait_until(lambda: engine.entered.is_set(), "first call at the gate")
    batched = [asyncio.ensure_future(batcher.submit(*cloud)) for cloud in clouds[1:]]
    await wait_until(lambda: batcher.queue_depth == 3, "three pairs queued")
    engine.gate.set()
    results = await asyncio.gather(blocker, *batched)
    await batcher.close(grace_s=10)
    assert engine.calls == [1, 3]
    for (source, target), result in zip(clouds, results, strict=True):
        rotation, translation = engine.engine.run(source[None], target[None])
        np.testing.assert_allclose(result.rotation, rotation[0], atol=1e-4)
        np.testing.assert_allclose(result.translation, translation[0], atol=1e-4)


async def test_pairs_of_different_sizes_run_in_separate_calls(tiny_model, gated_engine):
    engine = gated_engine(OnnxEngine(tiny_model))
    batcher = MicroBatcher(engine, max_batch_size=8, max_queue_size=8)
    batcher.start()
    rng = np.random.default_rng(1)
    first = asyncio.ensure_future(batcher.submit(rng.normal(size=(10, 3)), rng.normal(size=(10, 3))))
    await wait_until(lambda: engine.entered.is_set(), "first call at the gate")
    shapes = [(16, 16), (16, 16), (32, 16), (16, 16)]
    rest = [asyncio.ensure_future(batcher.submit(rng.normal(size=(n, 3)), rng.normal(size=(m, 3)))) for n, m in shapes]
    await wait_until(lambda: batcher.queue_depth == 4, "four pairs queued")
    engine.gate.set()
    results = await asyncio.gather(first, *rest)
    await batcher.close(grace_s=10)
    assert engine.calls == [1, 3, 1]
    assert [result.batch_size for result in results] == [1, 3, 3, 1, 3]


async def test_a_full_queue_answers_429_with_retry_after(serve, tiny_model, gated_engine):
    engine = gated_engine(OnnxEngine(tiny_model))
    async with serve(settings_for(tiny_model, max_queue_size=2), engines=[engine]) as (app, client):
        batcher = app.state.service.models["object"].batcher
        running = asyncio.ensure_future(client.post("/register", json=payload(0)))
        await wait_until(lambda: engine.entered.is_set(), "first call at the gate")
        queued = [asyncio.ensure_future(client.post("/register", json=payload(seed))) for seed in (1, 2)]
        await wait_until(lambda: batcher.queue_depth == 2, "queue full")
        rejected = await client.post("/register", json=payload(3))
        health = (await client.get("/health")).json()
        engine.gate.set()
        accepted = await asyncio.gather(running, *queued)
        metrics = metric_samples((await client.get("/metrics")).text)
    assert rejected.status_code == 429
    # Two queued pairs fit one batch of 8, so two batches are ahead (that one and the running
    # one), at the starting estimate of 1 s per call (no call has finished yet).
    assert rejected.headers["retry-after"] == "2"
    assert "queue is full; retry after 2 s" in rejected.json()["detail"]
    assert health["queue_depth"] == 2 and health["in_flight"] == 3
    assert [response.status_code for response in accepted] == [200, 200, 200]
    assert metrics["ifnet_batcher_rejections_total{model=object,reason=queue_full}"] == 1
    assert metrics["ifnet_http_requests_total{method=POST,route=/register,status=429}"] == 1


def test_retry_after_is_the_batches_ahead_times_a_recent_call_over_the_model_calls():
    batcher = MicroBatcher(object(), max_batch_size=4, max_queue_size=16, model_calls=2)
    batcher._batch_seconds = 3.0  # the running estimate of one call
    for waiting, seconds in ((0, 2), (4, 3), (5, 5), (9, 6), (16, 8)):
        batcher._waiting = waiting  # ceil(waiting / 4) batches queued, plus the one running
        assert batcher.retry_after_s() == seconds, waiting
    batcher._batch_seconds = 0.01
    assert batcher.retry_after_s() == 1  # never "retry after 0 s"
    batcher._executor.shutdown()


async def test_requests_beyond_the_in_flight_limit_get_429_before_their_body_is_read(serve, tiny_model, gated_engine):
    engine = gated_engine(OnnxEngine(tiny_model))
    async with serve(settings_for(tiny_model, max_in_flight=2), engines=[engine]) as (app, client):
        service = app.state.service
        running = asyncio.ensure_future(client.post("/register", json=payload(0)))
        await wait_until(lambda: engine.entered.is_set(), "first call at the gate")
        queued = asyncio.ensure_future(client.post("/register", json=payload(1)))
        await wait_until(lambda: service.models["object"].batcher.queue_depth == 1, "second pair queued")
        # Not JSON at all: a 429 rather than a 400 shows that the body was never read.
        rejected = await client.post("/register", content=b"{not json", headers={"content-type": "application/json"})
        v2_rejected = await client.post("/v2/models/object/infer", content=b"{not json")
        engine.gate.set()
        accepted = await asyncio.gather(running, queued)
        after = await client.post("/register", json=payload(2))
        health = (await client.get("/health")).json()
    assert [r.status_code for r in (rejected, v2_rejected)] == [429, 429]
    assert "2 registration requests are already in progress" in rejected.json()["detail"]
    assert int(rejected.headers["retry-after"]) >= 1
    assert [r.status_code for r in accepted] == [200, 200]
    assert after.status_code == 200, after.text  # the slots were given back
    assert health["in_flight"] == 0


async def test_a_request_that_waits_too_long_gets_504_and_leaves_the_batch(serve, tiny_model, gated_engine):
    engine = gated_engine(OnnxEngine(tiny_model))
    async with serve(settings_for(tiny_model, request_timeout_s=1.0), engines=[engine]) as (app, client):
        batcher = app.state.service.models["object"].batcher
        running = asyncio.ensure_future(client.post("/register", json=payload(0)))
        await wait_until(lambda: engine.entered.is_set(), "first call at the gate")
        waiting = await client.post("/register", json=payload(1))  # queued behind the gate, times out
        assert batcher.queue_depth == 0  # the timed-out pair no longer counts as queued
        engine.gate.set()
        timed_out_first = await running  # it was at the gate just as long: 504 too, its result dropped
        after = await client.post("/register", json=payload(2))
    # The request's deadline answers, and its pair leaves the batcher's queue (counted as cancelled).
    assert waiting.status_code == 504 and "within the request timeout of 1 s" in waiting.json()["detail"]
    assert timed_out_first.status_code == 504
    assert after.status_code == 200
    # The timed-out pair never reached the model: the call after the gate ran pair 2 alone.
    assert engine.calls == [1, 1]


async def test_a_client_that_disconnects_does_not_poison_the_batch(serve, tiny_model, gated_engine):
    engine = gated_engine(OnnxEngine(tiny_model))
    async with serve(settings_for(tiny_model), engines=[engine]) as (app, client):
        batcher = app.state.service.models["object"].batcher
        running = asyncio.ensure_future(client.post("/register", json=payload(0)))
        await wait_until(lambda: engine.entered.is_set(), "first call at the gate")

        # A raw ASGI request whose client goes away while its pair waits in the queue.
        leaving, gone, sent = vanishing_request(app, json.dumps(payload(1)).encode())
        queued_behind = asyncio.ensure_future(client.post("/register", json=payload(2)))
        await wait_until(lambda: batcher.queue_depth == 2, "two pairs queued")
        gone.set()
        await leaving
        assert batcher.queue_depth == 1
        engine.gate.set()
        responses = await asyncio.gather(running, queued_behind)
        metrics = metric_samples((await client.get("/metrics")).text)
    assert sent[0]["status"] == 499
    assert [response.status_code for response in responses] == [200, 200]
    assert engine.calls == [1, 1]  # the departed pair was skipped
    assert metrics["ifnet_http_requests_total{method=POST,route=/register,status=499}"] == 1


async def test_a_failing_model_call_is_a_500_and_the_worker_carries_on(serve, tiny_model):
    class FlakyEngine:
        def __init__(self):
            self.engine = OnnxEngine(tiny_model)
            self.info = self.engine.info
            self.failures = 1

        def run(self, source, target, beside=False):
            if self.failures:
                self.failures -= 1
                raise RuntimeError("simulated ORT failure")
            return self.engine.run(source, target)

    async with serve(settings_for(tiny_model), engines=[FlakyEngine()]) as (app, client):
        failed = await client.post("/register", json=payload(0))
        recovered = await client.post("/register", json=payload(0))
    assert failed.status_code == 500 and "simulated ORT failure" in failed.json()["detail"]
    assert recovered.status_code == 200


async def test_shutdown_finishes_queued_work_then_refuses_new_work(tiny_model, gated_engine):
    engine = gated_engine(OnnxEngine(tiny_model))
    batcher = MicroBatcher(engine, max_batch_size=2, max_queue_size=8)
    batcher.start()
    rng = np.random.default_rng(2)
    submitted = [
        asyncio.ensure_future(batcher.submit(rng.normal(size=(20, 3)), rng.normal(size=(20, 3)))) for _ in range(5)
    ]
    await wait_until(lambda: engine.at_gate + batcher.queue_depth == 5, "every pair at the gate or queued")
    closing = asyncio.ensure_future(batcher.close(grace_s=30))
    await wait_until(lambda: not batcher.accepting, "closing started")
    with pytest.raises(ShuttingDownError):
        await batcher.submit(rng.normal(size=(20, 3)), rng.normal(size=(20, 3)))
    engine.gate.set()
    results = await asyncio.gather(*submitted)
    await closing
    assert len(results) == 5 and sum(engine.calls) == 5 and max(engine.calls) == 2


async def test_shutdown_grace_period_fails_leftover_work_cleanly(tiny_model, gated_engine):
    engine = gated_engine(OnnxEngine(tiny_model))  # the gate never opens
    batcher = MicroBatcher(engine, max_batch_size=1, max_queue_size=8)
    batcher.start()
    rng = np.random.default_rng(3)
    submitted = [
        asyncio.ensure_future(batcher.submit(rng.normal(size=(20, 3)), rng.normal(size=(20, 3)))) for _ in range(2)
    ]
    await wait_until(lambda: engine.at_gate == 1 and batcher.queue_depth == 1, "one running, one queued")
    await batcher.close(grace_s=0.05)
    outcomes = await asyncio.gather(*submitted, return_exceptions=True)
    engine.gate.set()  # release the abandoned ORT thread
    assert all(isinstance(outcome, ShuttingDownError) for outcome in outcomes)


async def test_queue_full_and_inference_errors_are_typed(tiny_model):
    class Broken:
        info = OnnxEngine(tiny_model).info

        def run(self, source, target, beside=False):
            return np.zeros((1, 2, 2)), np.zeros((1, 3))  # wrong shapes

    batcher = MicroBatcher(Broken(), max_batch_size=1, max_queue_size=1)
    rng = np.random.default_rng(4)
    first = asyncio.ensure_future(batcher.submit(rng.normal(size=(8, 3)), rng.normal(size=(8, 3))))
    await asyncio.sleep(0)
    with pytest.raises(QueueFullError) as caught:
        await batcher.submit(rng.normal(size=(8, 3)), rng.normal(size=(8, 3)))
    assert caught.value.retry_after_s >= 1
    batcher.start()
    with pytest.raises(InferenceError, match="rotation"):
        await first
    await batcher.close(grace_s=1)


async def test_start_beside_returns_once_its_call_is_taken_up_and_not_while_it_waits(tiny_model, gated_engine):
    engine = gated_engine(OnnxEngine(tiny_model, threads=2, model_calls=2))
    batcher = MicroBatcher(engine, max_batch_size=1, max_queue_size=4)
    batcher.start()
    rng = np.random.default_rng(5)
    source, target = (rng.normal(size=(64, 3)).astype(np.float32) for _ in range(2))
    held = asyncio.ensure_future(batcher.submit(source, target))
    await wait_until(engine.entered.is_set, "the first call at the gate")
    starting = asyncio.ensure_future(batcher.start_beside(source, target))
    await wait_until(lambda: batcher.queue_depth == 1, "the second pair queued")
    await asyncio.sleep(0.05)
    assert not starting.done()  # its pair waits behind the held call: its work would run alone
    engine.gate.set()
    answer = await starting
    prediction, first = await answer, await held
    np.testing.assert_allclose(prediction.rotation, first.rotation, atol=1e-5)  # the same pair, fewer threads
    assert engine.besides == [False, True]

    # cancelled while its pair waits: the pair leaves the queue
    engine.gate.clear()
    engine.entered.clear()
    held = asyncio.ensure_future(batcher.submit(source, target))
    await wait_until(engine.entered.is_set, "the first call at the gate")
    starting = asyncio.ensure_future(batcher.start_beside(source, target))
    await wait_until(lambda: batcher.queue_depth == 1, "the second pair queued")
    starting.cancel()
    with pytest.raises(asyncio.CancelledError):
        await starting
    await wait_until(lambda: batcher.queue_depth == 0, "the cancelled pair gone from the queue")
    engine.gate.set()
    await held
    assert engine.besides == [False, True, False]
    await batcher.close(grace_s=1)


async def test_model_calls_run_side_by_side_and_every_pair_gets_its_own_answer(tiny_model):
    engine = OnnxEngine(tiny_model, threads=2, model_calls=2)
    both_inside = threading.Barrier(2, timeout=30)  # breaks (a failed call) if calls never overlap

    class Paired:
        info = engine.info

        def run(self, source, target, beside=False):
            both_inside.wait()
            return engine.run(source, target)

    batcher = MicroBatcher(Paired(), max_batch_size=1, max_queue_size=8, model_calls=2)
    batcher.start()
    pairs = [tuple(cloud.astype(np.float32) for cloud in pair(seed)) for seed in range(4)]
    results = await asyncio.gather(*(batcher.submit(source, target) for source, target in pairs))
    await batcher.close(grace_s=5)
    for (source, target), result in zip(pairs, results, strict=True):
        rotation, translation = engine.run(source[None], target[None])
        assert np.allclose(result.rotation, rotation[0], atol=1e-6) and result.batch_size == 1
        assert np.allclose(result.translation, translation[0], atol=1e-6)
    assert batcher.queue_depth == 0


async def test_a_batch_delay_lets_a_batch_fill_up(tiny_model):
    """With max_batch_delay_ms, the worker waits for more pairs after the first (until the batch is full)."""
    engine = OnnxEngine(tiny_model)
    calls = []

    class Recording:
        info = engine.info

        def run(self, source, target, beside=False):
            calls.append(len(source))
            return engine.run(source, target)

    batcher = MicroBatcher(Recording(), max_batch_size=3, max_queue_size=8, max_batch_delay_ms=60_000)
    batcher.start()
    rng = np.random.default_rng(5)
    first = asyncio.ensure_future(batcher.submit(rng.normal(size=(16, 3)), rng.normal(size=(16, 3))))
    await wait_until(lambda: batcher.queue_depth == 0, "first pair taken by the waiting worker")
    later = [
        asyncio.ensure_future(batcher.submit(rng.normal(size=(16, 3)), rng.normal(size=(16, 3)))) for _ in range(2)
    ]
    results = await asyncio.gather(first, *later)  # a full batch does not wait out the minute
    await batcher.close(grace_s=5)
    assert calls == [3] and [result.batch_size for result in results] == [3, 3, 3]


async def test_the_timeout_bounds_the_whole_request_and_parsing_leaves_the_loop_free(serve, tiny_model, monkeypatch):
    """Parsing that takes too long (a huge body on a busy machine) is answered 504 on time, and
    /health answers meanwhile: JSON bodies are parsed in a worker thread, not on the event loop."""
    release = threading.Event()
    parse = RegisterRequest.model_validate_json

    def slow_parse(data, *args, **kwargs):
        release.wait(timeout=30)
        return parse(data, *args, **kwargs)

    async with serve(settings_for(tiny_model, request_timeout_s=0.5)) as (app, client):
        monkeypatch.setattr(RegisterRequest, "model_validate_json", slow_parse)
        slow = asyncio.ensure_future(client.post("/register", json=payload(0)))
        health = await client.get("/health")
        answered = await slow
        release.set()
        monkeypatch.undo()
        after = await client.post("/register", json=payload(1))
    assert health.status_code == 200
    assert answered.status_code == 504 and "within the request timeout of 0.5 s" in answered.json()["detail"]
    assert after.status_code == 200


class RecordingEngine:
    """Identity answers; records each call's batch size, optionally sleeping or waiting at a gate."""

    def __init__(self, sleep_s: float = 0.0, gate: threading.Event | None = None):
        self.calls: list[int] = []
        self.sleep_s, self.gate = sleep_s, gate

    def run(self, source, target, beside=False):
        if self.gate is not None:
            assert self.gate.wait(timeout=60), "the test never opened the gate"
        time.sleep(self.sleep_s)
        self.calls.append(len(source))
        return np.tile(np.eye(3), (len(source), 1, 1)), np.zeros((len(source), 3))


def small_pair() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    return rng.normal(size=(16, 3)), rng.normal(size=(16, 3))


async def test_the_batch_delay_counts_from_the_first_pair_not_from_each_arrival():
    """A batch waits at most max_batch_delay_ms after its first pair: later arrivals do not extend it."""
    engine = RecordingEngine()
    batcher = MicroBatcher(engine, max_batch_size=8, max_queue_size=8, max_batch_delay_ms=1000)
    batcher.start()
    first = asyncio.ensure_future(batcher.submit(*small_pair()))
    await asyncio.sleep(0.5)  # well inside the first pair's second
    second = asyncio.ensure_future(batcher.submit(*small_pair()))
    await asyncio.sleep(0.8)  # 1.3 s: the batch left at 1.0 s; timed from the second pair it would wait to 1.5
    third = asyncio.ensure_future(batcher.submit(*small_pair()))
    await asyncio.gather(first, second, third)
    await batcher.close(grace_s=5)
    assert engine.calls == [2, 1]


async def test_a_pair_that_times_out_in_the_queue_is_counted_out_once():
    gate = threading.Event()
    engine = RecordingEngine(gate=gate)
    batcher = MicroBatcher(engine, max_batch_size=8, max_queue_size=8)
    batcher.start()
    running = asyncio.ensure_future(batcher.submit(*small_pair()))
    await wait_until(lambda: batcher.queue_depth == 0 and batcher._running == 1, "first pair taken")
    with pytest.raises(RequestTimeoutError):
        await batcher.submit(*small_pair(), timeout_s=0.05)  # waits behind the gated call, gives up
    queued = asyncio.ensure_future(batcher.submit(*small_pair()))
    await wait_until(lambda: batcher.queue_depth == 1, "third pair queued")
    gate.set()
    await asyncio.gather(running, queued)
    assert batcher.queue_depth == 0
    started = time.perf_counter()
    await batcher.close(grace_s=5)
    assert time.perf_counter() - started < 1.0, "close() waited for a pair that was already gone"
    assert engine.calls == [1, 1]


async def test_the_call_time_estimate_follows_the_calls_that_ran():
    """Retry-After uses a running average of model calls: 0.8 of the last estimate, 0.2 of the new call."""
    batcher = MicroBatcher(RecordingEngine(sleep_s=0.2), max_batch_size=1, max_queue_size=4)
    batcher.start()
    answer = await batcher.submit(*small_pair())
    await batcher.close(grace_s=5)
    assert batcher._batch_seconds == pytest.approx(0.8 * 1.0 + 0.2 * answer.inference_ms / 1000, rel=0.05)
    assert answer.inference_ms >= 200
