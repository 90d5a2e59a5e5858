"""Property tests over file and archive bodies: random bytes, truncations and bit flips of valid
PLY, PCD, NPY and NPZ files.

Decoding one (service.formats) ends in a cloud or in InvalidInput / UnsupportedFormat (422 / 415),
never another exception (a 500), and allocates at most MEMORY_FACTOR x the body limit beyond the
body itself (traced with tracemalloc). Over HTTP, the same bodies as multipart parts or raw
bodies never get a 5xx.
"""

import io
import tracemalloc

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pypcd4 import Encoding, PointCloud
from test_hostile_files import npy_bytes, ply_bytes

from service.formats import UnsupportedFormat, read_cloud, read_pair
from service.validation import InvalidInput

BODY_LIMIT = 1 << 20  # the body limit of these tests (IFNET_MAX_BODY_BYTES)
MEMORY_FACTOR = 4  # the stated bound: decoding allocates at most 4x the body limit
MAX_POINTS = 500_000  # the default point limit, so that headers may claim large clouds
POINTS = (np.random.default_rng(2).integers(-40, 40, size=(200, 3)) / 8.0).astype(np.float32)


def pcd(encoding: Encoding) -> bytes:
    stream = io.BytesIO()
    PointCloud.from_xyz_points(POINTS).save(stream, encoding=encoding)
    return stream.getvalue()


def npz(compressed: bool) -> bytes:
    stream = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(stream, source=POINTS, target=POINTS + 1)
    return stream.getvalue()


VALID_CLOUDS = {
    "ply-ascii": ply_bytes(POINTS, text=True),
    "ply-binary": ply_bytes(POINTS, text=False),
    "ply-mesh": ply_bytes(POINTS, text=True, faces=20),
    "pcd-ascii": pcd(Encoding.ASCII),
    "pcd-binary": pcd(Encoding.BINARY),
    "pcd-compressed": pcd(Encoding.BINARY_COMPRESSED),
    "npy": npy_bytes(POINTS),
}
VALID_PAIRS = {
    "npz-stored": npz(False),
    "npz-deflated": npz(True),
    "npy-pair": npy_bytes(np.stack([POINTS, POINTS + 1])),
}
VALID = {**VALID_CLOUDS, **VALID_PAIRS}


@st.composite
def damaged(draw) -> tuple[str, bytes]:
    """(kind, body): a valid file cut short, with bits flipped or bytes overwritten, or random bytes."""
    kind = draw(st.sampled_from(sorted(VALID)))
    data = bytearray(VALID[kind])
    how = draw(st.sampled_from(["truncate", "flip", "overwrite", "random", "mixed"]))
    if how in ("truncate", "mixed"):
        data = data[: draw(st.integers(0, len(data)))]
    if how in ("flip", "mixed") and data:
        for _ in range(draw(st.integers(1, 8))):
            position = draw(st.integers(0, len(data) - 1))
            data[position] ^= 1 << draw(st.integers(0, 7))
    if how == "overwrite" and data:
        position = draw(st.integers(0, len(data) - 1))
        patch = draw(st.binary(min_size=1, max_size=16))
        data[position : position + len(patch)] = patch
    if how == "random":
        prefix = draw(st.sampled_from([b"", b"ply\n", b"# .PCD v0.7\n", b"\x93NUMPY\x01\x00", b"PK\x03\x04"]))
        data = bytearray(prefix + draw(st.binary(max_size=2048)))
    return kind, bytes(data)


def decode(kind: str, data: bytes):
    if kind in VALID_CLOUDS:
        return read_cloud(data, "source", MAX_POINTS, BODY_LIMIT)
    return read_pair(data, MAX_POINTS)


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(damaged())
def test_damaged_files_decode_or_are_refused_in_bounded_memory(case):
    kind, data = case
    tracemalloc.start()
    try:
        try:
            decode(kind, data)
        except (InvalidInput, UnsupportedFormat) as refusal:
            assert str(refusal)
            assert len(str(refusal)) < 1000
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak <= MEMORY_FACTOR * BODY_LIMIT, f"{kind}: {peak} bytes traced for a {len(data)}-byte body"


def test_every_valid_file_decodes():
    for kind, data in VALID.items():
        decode(kind, data)


@pytest.fixture(scope="module")
def client(tiny_model):
    """An in-process app on the tiny model, with the body limit above."""
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.settings import Settings

    app = create_app(Settings(model_path=tiny_model, max_body_bytes=BODY_LIMIT, warmup=False))
    with TestClient(app) as test_client:
        yield test_client


@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture]
)
@given(damaged())
def test_damaged_bodies_never_get_a_5xx(client, case):
    kind, data = case
    if kind in VALID_CLOUDS:
        other = VALID["npy"]
        answer = client.post("/register", files={"source": ("s", data), "target": ("t", other)})
    else:
        answer = client.post("/register", content=data, headers={"Content-Type": "application/octet-stream"})
    assert answer.status_code < 500, f"{kind}: {answer.status_code} {answer.text[:300]}"
    if answer.status_code != 200:
        assert answer.json()["detail"]
