"""Security properties of the service's input handling.

- No pickle anywhere in input parsing: the source of service/ never imports a pickle-based
  loader nor calls np.load without allow_pickle=False, and pickled uploads (NPY object arrays,
  in every way a cloud can arrive) are refused without anything being unpickled.
- The API key is compared in constant time (secrets.compare_digest, never ==), and a request
  without the key is answered 401 before its body is read.
- The body size limit is enforced before parsing: a declared Content-Length over the limit is
  answered 413 without reading the body, a streamed one without calling any parser.
- A connection that does not complete a request head in time (silent, or trickling its headers,
  slowloris) is closed; the body's own time is bounded by the request timeout instead.

Related checks elsewhere: basic 401/413 behaviour in test_api.py, the reader-level
pickle refusal in test_formats.py, the non-root container in test_container.py.
"""

import asyncio
import http.client
import io
import json
import pickle
import socket
import time
import zipfile
from pathlib import Path

import httpx
import numpy as np
import pytest
from conftest import asgi_scope, register_head, service_process

import service
from service.settings import Settings

pytestmark = pytest.mark.anyio

SERVICE_DIR = Path(service.__file__).resolve().parent
REPO_ROOT = SERVICE_DIR.parent
SOURCE = np.random.default_rng(3).normal(size=(100, 3))
TARGET = SOURCE + [0.5, 0.0, 0.0]

# ---------------------------------------------------------------- pickled uploads over HTTP

UNPICKLED: list[str] = []


def record_unpickling(message: str) -> None:
    UNPICKLED.append(message)


class Payload:
    """Records that it was unpickled (a real attack would run a command here instead)."""

    def __reduce__(self):
        return (record_unpickling, ("payload ran",))


def pickled_npy(array: np.ndarray) -> bytes:
    stream = io.BytesIO()
    np.save(stream, array, allow_pickle=True)
    return stream.getvalue()


def object_array(shape: tuple[int, ...]) -> np.ndarray:
    array = np.empty(shape, dtype=object)
    array.flat[0] = Payload()
    for index in range(1, array.size):
        array.flat[index] = 0.0
    return array


@pytest.fixture
def no_unpickling(monkeypatch):
    """Every way numpy (or anything else) could unpickle now fails the test loudly."""
    calls: list[str] = []

    def refuse(name):
        def call(*args, **kwargs):
            calls.append(name)
            raise AssertionError(f"pickle.{name} was called while parsing a request")

        return call

    for name in ("load", "loads"):
        monkeypatch.setattr(pickle, name, refuse(name))
    UNPICKLED.clear()
    yield calls
    UNPICKLED.clear()


def npz_with(**arrays: bytes) -> bytes:
    stream = io.BytesIO()
    with zipfile.ZipFile(stream, "w") as archive:
        for name, data in arrays.items():
            archive.writestr(f"{name}.npy", data)
    return stream.getvalue()


def test_the_payload_would_run_if_unpickled():
    """Guard: the payload used below really executes when numpy is allowed to unpickle it."""
    UNPICKLED.clear()
    np.load(io.BytesIO(pickled_npy(object_array((2, 3)))), allow_pickle=True)
    assert UNPICKLED == ["payload ran"]
    UNPICKLED.clear()


async def test_pickled_uploads_are_refused_without_unpickling(serve, tiny_model, no_unpickling):
    plain = io.BytesIO()
    np.save(plain, TARGET)
    raw_pickle = pickle.dumps(Payload())
    async with serve(Settings(model_path=tiny_model)) as (app, client):
        answers = {
            "multipart npy": await client.post(
                "/register",
                files={"source": ("s.npy", pickled_npy(object_array((100, 3)))), "target": ("t.npy", plain.getvalue())},
            ),
            "multipart raw pickle": await client.post(
                "/register", files={"source": ("s.pkl", raw_pickle), "target": ("t.npy", plain.getvalue())}
            ),
            "raw npy body": await client.post(
                "/register",
                content=pickled_npy(object_array((2, 100, 3))),
                headers={"content-type": "application/x-npy"},
            ),
            "raw npz body": await client.post(
                "/register",
                content=npz_with(source=pickled_npy(object_array((100, 3))), target=plain.getvalue()),
                headers={"content-type": "application/x-npz"},
            ),
            "raw pickle body": await client.post(
                "/register", content=raw_pickle, headers={"content-type": "application/octet-stream"}
            ),
        }
        still_serving = await client.post("/register", json={"source": SOURCE.tolist(), "target": TARGET.tolist()})
    for what, response in answers.items():
        assert response.status_code in (415, 422), f"{what}: {response.status_code} {response.text}"
    for what in ("multipart npy", "raw npy body", "raw npz body"):
        assert "pickle" in answers[what].json()["detail"], what
    assert no_unpickling == [] and UNPICKLED == []
    assert still_serving.status_code == 200


# ---------------------------------------------------------------- raw ASGI helpers


async def call_asgi(app, scope: dict, chunks: list[bytes]) -> tuple[int, dict, list[int]]:
    """Run one request; returns status, JSON body, and how many body chunks the app pulled."""
    pulled: list[int] = []
    sent: list[dict] = []
    answered = asyncio.Event()

    async def receive() -> dict:
        if len(pulled) < len(chunks):
            pulled.append(len(chunks[len(pulled)]))
            return {"type": "http.request", "body": chunks[len(pulled) - 1], "more_body": len(pulled) < len(chunks)}
        await answered.wait()  # the client stays connected until it has its answer
        return {"type": "http.disconnect"}

    async def send(message: dict) -> None:
        sent.append(message)
        if message["type"] == "http.response.body" and not message.get("more_body", False):
            answered.set()

    await app(scope, receive, send)
    body = b"".join(message.get("body", b"") for message in sent if message["type"] == "http.response.body")
    return sent[0]["status"], json.loads(body), pulled


# ---------------------------------------------------------------- API key


async def test_the_api_key_is_compared_in_constant_time(serve, tiny_model, monkeypatch):
    import service.dependencies as dependencies

    compared: list[tuple[bytes, bytes]] = []
    real_compare = dependencies.secrets.compare_digest

    def spy(given, expected):
        compared.append((given, expected))
        return real_compare(given, expected)

    monkeypatch.setattr(dependencies.secrets, "compare_digest", spy)
    key = "correct-horse-battery-staple"
    body = {"source": SOURCE.tolist(), "target": TARGET.tolist()}
    async with serve(Settings(model_path=tiny_model, api_key=key)) as (app, client):
        statuses = [
            (await client.post("/register", json=body, headers=headers)).status_code
            for headers in (
                {"X-API-Key": "x"},  # shorter
                {"X-API-Key": key[:-1] + "X"},  # same length, last byte wrong
                {"X-API-Key": key + "-and-more"},  # the key is a prefix of it
                {"X-API-Key": key},
                {"Authorization": f"Bearer {key}"},
                {"Authorization": "Bearer wrong"},
            )
        ]
    assert statuses == [401, 401, 401, 200, 200, 401]
    assert len(compared) == 6  # every key given went through compare_digest
    assert all(isinstance(given, bytes) and expected == key.encode() for given, expected in compared)


def v2_body(source: np.ndarray, target: np.ndarray) -> dict:
    return {
        "inputs": [
            {"name": name, "datatype": "FP32", "shape": list(cloud.shape), "data": cloud.ravel().tolist()}
            for name, cloud in (("source", source), ("target", target))
        ]
    }


@pytest.mark.parametrize(
    "path, payload",
    [
        ("/register", {"source": SOURCE.tolist(), "target": TARGET.tolist()}),
        ("/v2/models/object/infer", v2_body(SOURCE, TARGET)),
    ],
)
async def test_a_request_without_the_key_is_refused_before_its_body_is_read(serve, tiny_model, path, payload):
    body = json.dumps(payload).encode()
    chunks = [body[:1000], body[1000:]]
    headers = {"content-type": "application/json", "content-length": str(len(body))}
    async with serve(Settings(model_path=tiny_model, api_key="k")) as (app, client):
        status, answer, pulled = await call_asgi(app, asgi_scope(path, headers), chunks)
        authorised, _, pulled_authorised = await call_asgi(app, asgi_scope(path, {**headers, "x-api-key": "k"}), chunks)
    assert status == 401 and "API key" in (answer.get("detail") or answer.get("error"))
    assert pulled == []  # not one byte of the body was read
    assert authorised == 200 and pulled_authorised == [1000, len(body) - 1000]


# ---------------------------------------------------------------- body limit


@pytest.mark.parametrize("content_type", ["application/json", "application/x-npy", "multipart/form-data; boundary=x"])
async def test_a_declared_length_over_the_limit_is_refused_before_reading(serve, tiny_model, content_type):
    headers = {"content-type": content_type, "content-length": str(10_001)}
    async with serve(Settings(model_path=tiny_model, max_body_bytes=10_000)) as (app, client):
        status, answer, pulled = await call_asgi(app, asgi_scope("/register", headers), [b"x" * 10_001])
        v2_status, v2_answer, v2_pulled = await call_asgi(
            app, asgi_scope("/v2/models/object/infer", headers), [b"x" * 10_001]
        )
    assert status == v2_status == 413
    assert pulled == v2_pulled == []
    assert "larger than the limit of 10000 bytes" in answer["detail"] and answer["errors"][0]["field"] == "body"


async def test_a_streamed_body_over_the_limit_never_reaches_a_parser(serve, tiny_model, monkeypatch):
    import service.uploads as uploads

    parsed: list[str] = []
    real_read_pair = uploads.read_pair

    def recording_read_pair(*args, **kwargs):
        parsed.append("npy")
        return real_read_pair(*args, **kwargs)

    real_model = uploads.RegisterRequest

    class Spy:
        @staticmethod
        def model_validate_json(data, *args, **kwargs):
            parsed.append("json")
            return real_model.model_validate_json(data, *args, **kwargs)

    monkeypatch.setattr(uploads, "RegisterRequest", Spy)
    monkeypatch.setattr(uploads, "read_pair", recording_read_pair)

    json_body = json.dumps({"source": SOURCE.tolist(), "target": TARGET.tolist()}).encode()
    npy = io.BytesIO()
    np.save(npy, np.stack([SOURCE, TARGET]))
    limit = 2_000
    async with serve(Settings(model_path=tiny_model, max_body_bytes=limit, min_points=8)) as (app, client):
        results = []
        for content_type, body in (("application/json", json_body), ("application/x-npy", npy.getvalue())):
            assert len(body) > 2 * limit
            chunks = [body[start : start + 500] for start in range(0, len(body), 500)]
            results.append(await call_asgi(app, asgi_scope("/register", {"content-type": content_type}), chunks))
        few = np.round(SOURCE[:16], 3).tolist()
        small = await client.post("/register", json={"source": few, "target": few})
    for status, answer, pulled in results:
        assert status == 413, answer
        assert sum(pulled) <= limit + 500  # reading stopped at the chunk that crossed the limit
    assert parsed == ["json"]  # only the small request below the limit was parsed
    assert small.status_code == 200


# ---------------------------------------------------------------- connections that never send a request


def read_until_closed(connection: socket.socket) -> bytes:
    received = b""
    while chunk := connection.recv(65536):  # the socket's timeout is the hang guard
        received += chunk
    return received


def trickle(connection: socket.socket, data: bytes, seconds: float) -> None:
    """Send data a few bytes at a time over `seconds`, stopping quietly if the server closes."""
    pieces = [data[i : i + 4] for i in range(0, len(data), 4)]
    try:
        for piece in pieces:
            connection.sendall(piece)
            time.sleep(seconds / len(pieces))
    except OSError:  # closed by the server mid-trickle
        pass


@pytest.mark.slow
def test_connections_must_send_their_request_head_in_time(tmp_path, tiny_model):
    """uvicorn alone keeps a silent or slowloris connection open forever; the service closes it."""
    head_timeout_s = 1.5
    body = json.dumps({"source": SOURCE.tolist(), "target": TARGET.tolist()}).encode()
    head = register_head(body)
    with service_process(tmp_path, tiny_model, request_head_timeout_s=str(head_timeout_s)) as (_, url, log):
        address = ("127.0.0.1", httpx.URL(url).port)

        with socket.create_connection(address, timeout=10) as silent:
            started = time.monotonic()
            assert read_until_closed(silent) == b""  # closed without an answer: nothing was asked
            assert head_timeout_s <= time.monotonic() - started < head_timeout_s + 3

        with socket.create_connection(address, timeout=10) as slowloris:
            started = time.monotonic()
            trickle(slowloris, head[:-4], seconds=4 * head_timeout_s)  # every byte would reset uvicorn's keep-alive
            answer = read_until_closed(slowloris)
            assert answer.startswith(b"HTTP/1.1 408 ") and b"request headers not received" in answer
            assert time.monotonic() - started < head_timeout_s + 2  # cut off mid-trickle

        with socket.create_connection(address, timeout=30) as slow_body:  # the head in time, the body slowly
            slow_body.sendall(head)
            trickle(slow_body, body, seconds=2 * head_timeout_s)
            assert slow_body.recv(65536).startswith(b"HTTP/1.1 200 ")

        kept_alive = http.client.HTTPConnection(*address, timeout=30)
        sockets = []
        for _ in range(3):  # requests on one connection, each within the deadline of the last answer
            kept_alive.request("POST", "/register", body=body, headers={"Content-Type": "application/json"})
            response = kept_alive.getresponse()
            assert response.status == 200, response.read()
            response.read()
            sockets.append(kept_alive.sock)
            time.sleep(0.2)
        assert all(used is sockets[0] for used in sockets)  # never reconnected behind the test's back
        trickle(kept_alive.sock, head[:-4], seconds=4 * head_timeout_s)  # the next head is timed as well
        assert read_until_closed(kept_alive.sock).startswith(b"HTTP/1.1 408 ")
        kept_alive.close()
    assert "request head incomplete" in log.read_text()


@pytest.mark.slow
def test_an_idle_connection_lives_until_the_head_deadline_not_less(tmp_path, tiny_model):
    """Clients keep idle connections for 5 s (httpx) or more; a server that closed them sooner raced
    their next request, which the client saw as a broken connection. The head deadline (10 s by
    default) is the one bound on an idle connection."""
    body = json.dumps({"source": SOURCE.tolist(), "target": TARGET.tolist()}).encode()
    with service_process(tmp_path, tiny_model) as (_, url, log):
        kept_alive = http.client.HTTPConnection("127.0.0.1", httpx.URL(url).port, timeout=30)
        sockets = []
        for pause_s in (0.0, 6.5):  # past uvicorn's own default keep-alive of 5 s
            time.sleep(pause_s)
            kept_alive.request("POST", "/register", body=body, headers={"Content-Type": "application/json"})
            response = kept_alive.getresponse()
            assert response.status == 200, response.read()
            response.read()
            sockets.append(kept_alive.sock)
        assert sockets[1] is sockets[0]  # the same connection, never reopened behind the test's back
        kept_alive.close()


def with_padding(head: bytes, size: int) -> bytes:
    """head with one more header whose value is `size` bytes long."""
    return head.replace(b"\r\n\r\n", b"\r\nX-Padding: " + b"p" * size + b"\r\n\r\n")


def test_request_heads_over_the_limit_are_refused_however_they_arrive(tmp_path, tiny_model):
    """h11 alone bounds a head only while it is incomplete: one that arrives in a single read
    passes at any size. The service answers 431 both ways, and never counts the body."""
    limit = 4096
    cloud = np.random.default_rng(5).normal(size=(1000, 3))
    body = json.dumps({"source": cloud.tolist(), "target": (cloud + 0.1).tolist()}).encode()
    assert len(body) > 10 * limit
    with service_process(tmp_path, tiny_model, max_head_bytes=str(limit)) as (_, url, log):
        address = ("127.0.0.1", httpx.URL(url).port)

        def answer(data: bytes, piece_bytes: int | None = None) -> bytes:
            """The server's answer to data sent at once, or in pieces a moment apart."""
            piece_bytes = piece_bytes or len(data)
            with socket.create_connection(address, timeout=30) as connection:
                try:
                    for start in range(0, len(data), piece_bytes):
                        connection.sendall(data[start : start + piece_bytes])
                        time.sleep(0.05 if piece_bytes < len(data) else 0)
                except OSError:  # closed by the server before all was sent
                    pass
                return read_until_closed_or_answered(connection)

        head = register_head(body)
        assert answer(with_padding(head, limit - 500) + body).startswith(b"HTTP/1.1 200 ")  # with its body, one read
        for data, piece_bytes in (
            (with_padding(head, 100_000) + body, None),  # the whole head in one read
            (with_padding(head, 10_000) + body, 1000),  # over several reads, each under the limit
            (with_padding(head, limit - len(head) - 12), None),  # one byte over
        ):
            refused = answer(data, piece_bytes)
            assert refused.startswith(b"HTTP/1.1 431 "), refused[:200]
            assert b"request head larger than 4096 bytes" in refused
        assert answer(with_padding(head, limit - len(head) - 13) + body).startswith(b"HTTP/1.1 200 ")  # exactly
    assert "request head over 4096 bytes" in log.read_text()


def read_until_closed_or_answered(connection: socket.socket) -> bytes:
    """An answer that closes the connection, or the first answer on a kept-alive one."""
    received = b""
    while chunk := connection.recv(65536):
        received += chunk
        head, _, rest = received.partition(b"\r\n\r\n")
        if rest and b"content-length:" in head.lower():
            length = int(head.lower().split(b"content-length:")[1].split(b"\r\n")[0])
            if len(rest) >= length:
                break
    return received


@pytest.mark.slow
def test_a_body_refused_unread_still_gets_its_answer(tmp_path, tiny_model):
    """A 401, 413 or 429 goes out before the body is read. When the client asked to close the
    connection (Python's urllib does), closing at once makes the kernel reset the body still
    arriving, and the client reports the reset instead of the answer: the service drains first,
    up to the body limit."""
    import urllib.error
    import urllib.request

    limit = 16_000_000
    with service_process(tmp_path, tiny_model, api_key="s3cret", max_body_bytes=str(limit)) as (_, url, log):
        request = urllib.request.Request(
            f"{url}/register", data=b"x" * 8_000_000, headers={"Content-Type": "application/json"}
        )
        for _ in range(3):
            with pytest.raises(urllib.error.HTTPError) as refused:  # a reset would be a URLError
                urllib.request.urlopen(request, timeout=30)
            assert refused.value.code == 401 and "API key" in refused.value.read().decode()
        for encoding, status in (("br", 415), ("gzip", 400)):  # refused by the app after one chunk
            request.add_header("X-API-Key", "s3cret")
            request.add_header("Content-Encoding", encoding)
            with pytest.raises(urllib.error.HTTPError) as refused:
                urllib.request.urlopen(request, timeout=30)
            assert refused.value.code == status, refused.value.read()

        # The drain is bounded: a declared length over the limit gets its 413 at once, and the
        # connection is cut once the limit's worth of body has been dropped.
        address = ("127.0.0.1", httpx.URL(url).port)
        with socket.create_connection(address, timeout=30) as connection:
            head = register_head(b"x" * 4 * limit).replace(b"\r\n\r\n", b"\r\nConnection: close\r\n\r\n")
            connection.sendall(head)
            assert connection.recv(65536).startswith(b"HTTP/1.1 413 ")
            sent = 0
            with pytest.raises(OSError):  # reset or broken pipe once the server stops reading
                for _ in range(4 * limit // 65536):
                    sent += connection.send(b"x" * 65536)
            assert limit <= sent < 2 * limit  # dropped up to the limit, then cut (plus socket buffers)


@pytest.mark.slow
def test_a_kept_alive_client_refused_before_its_body_arrived_is_answered_again(tmp_path, tiny_model):
    """An answer sent while the body still arrives closes the connection once the body is drained. A
    client that has sent the whole body by the time it reads the answer kept the connection for its
    next request, which met the closed connection: `connection: close` tells it to open another."""
    body = json.dumps({"source": SOURCE.tolist(), "target": TARGET.tolist()}).encode()
    with service_process(tmp_path, tiny_model) as (_, url, _), httpx.Client(base_url=url, timeout=30) as client:
        for _ in range(3):
            refused = client.post("/nope", content=b"x" * 4_000_000)  # 404 before the body is read
            assert refused.status_code == 404 and refused.headers["connection"] == "close"
            answer = client.post("/register", content=body, headers={"Content-Type": "application/json"})
            assert answer.status_code == 200, answer.text
            assert "connection" not in answer.headers  # a body read whole: kept alive


def test_uvicorn_and_h11_are_the_versions_the_connection_protocol_is_tested_on():
    """The protocol subclasses uvicorn's h11 protocol and reads h11's state: another version must
    fail here, loudly, before it fails subtly in production."""
    import tomllib
    from importlib.metadata import version

    from packaging.specifiers import SpecifierSet

    from service.protocol import TESTED_VERSIONS

    requirements = tomllib.loads((REPO_ROOT / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    for package, tested in TESTED_VERSIONS.items():
        assert f"{package}{tested}" in requirements["serve"], f"pyproject.toml must pin {package}{tested}"
        installed = version(package)
        assert installed in SpecifierSet(tested), (
            f"{package} {installed} is installed, but service/protocol.py is tested on {package}{tested}: "
            "run its tests on the new version, then widen TESTED_VERSIONS and pyproject.toml together"
        )
