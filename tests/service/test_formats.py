"""Reading uploaded clouds: PLY, PCD and NPY round trips, and the files the service must refuse."""

import io
import struct

import numpy as np
import pytest
from plyfile import PlyData, PlyElement
from pypcd4 import Encoding, PointCloud

from service.formats import UnsupportedFormat, detect_format, read_cloud, read_pair, write_ply
from service.validation import InvalidInput

# Multiples of 1/8: exact in every format, and compressible (pypcd4 falls back to uncompressed otherwise).
POINTS = (np.random.default_rng(0).integers(-40, 40, size=(50, 3)) / 8.0).astype(np.float32)
LIMIT = 1000


def ply_bytes(points: np.ndarray, text: bool, extra: str | None = None) -> bytes:
    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")] + ([(extra, "f4")] if extra else [])
    vertices = np.zeros(len(points), dtype=fields)
    for index, axis in enumerate("xyz"):
        vertices[axis] = points[:, index]
    stream = io.BytesIO()
    PlyData([PlyElement.describe(vertices, "vertex")], text=text).write(stream)
    return stream.getvalue()


def pcd_bytes(points: np.ndarray, encoding: Encoding) -> bytes:
    stream = io.BytesIO()
    PointCloud.from_xyz_points(points).save(stream, encoding=encoding)
    return stream.getvalue()


def npy_bytes(array: np.ndarray, allow_pickle: bool = False) -> bytes:
    stream = io.BytesIO()
    np.save(stream, array, allow_pickle=allow_pickle)
    return stream.getvalue()


@pytest.mark.parametrize(
    ("data", "kind"),
    [
        (ply_bytes(POINTS, text=True), "ply"),
        (ply_bytes(POINTS, text=False), "ply"),
        (ply_bytes(POINTS, text=False, extra="intensity"), "ply"),
        (pcd_bytes(POINTS, Encoding.ASCII), "pcd"),
        (pcd_bytes(POINTS, Encoding.BINARY), "pcd"),
        (pcd_bytes(POINTS, Encoding.BINARY_COMPRESSED), "pcd"),
        (npy_bytes(POINTS), "npy"),
        (npy_bytes(POINTS.astype(np.float64)), "npy"),
    ],
    ids=[
        "ply-ascii",
        "ply-binary",
        "ply-extra-property",
        "pcd-ascii",
        "pcd-binary",
        "pcd-compressed",
        "npy32",
        "npy64",
    ],
)
def test_round_trip(data, kind):
    assert detect_format(data) == kind
    points = read_cloud(data, "source", LIMIT)
    assert points.dtype == np.float64
    np.testing.assert_allclose(points, POINTS, rtol=1e-6, atol=1e-6)


def test_the_pcd_cases_cover_every_encoding():
    for encoding in ("ascii", "binary", "binary_compressed"):
        assert f"DATA {encoding}\n".encode() in pcd_bytes(POINTS, Encoding(encoding))


def test_write_ply_reads_back(tmp_path):
    path = tmp_path / "cloud.ply"
    write_ply(path, POINTS.astype(np.float64))
    np.testing.assert_array_equal(read_cloud(path.read_bytes(), "source", LIMIT), POINTS)


def test_pickled_npy_is_refused():
    data = npy_bytes(np.array([{"not": "points"}], dtype=object), allow_pickle=True)
    with pytest.raises(InvalidInput, match="pickle"):
        read_cloud(data, "source", LIMIT)


def test_wrong_npy_shape_and_nan_values_are_named():
    with pytest.raises(InvalidInput, match=r"N x 3, got shape \[50, 2\]") as caught:
        read_cloud(npy_bytes(POINTS[:, :2]), "target", LIMIT)
    assert caught.value.field == "target"
    with_nan = POINTS.copy()
    with_nan[7, 1] = np.nan
    with pytest.raises(InvalidInput, match="NaN or infinite.*index 7"):
        read_cloud(npy_bytes(with_nan), "target", LIMIT)


@pytest.mark.parametrize("encoding", [Encoding.ASCII, Encoding.BINARY, Encoding.BINARY_COMPRESSED])
def test_nan_rows_in_a_pcd_are_named_not_dropped(encoding):
    """Organised scans mark missing returns with NaN rows; the user decides what to do with them."""
    with_nan = POINTS.copy()
    with_nan[7] = np.nan
    with pytest.raises(InvalidInput, match="NaN or infinite.*index 7"):
        read_cloud(pcd_bytes(with_nan, encoding), "source", LIMIT)


def test_big_endian_binary_ply_reads_like_little_endian():
    vertices = np.zeros(len(POINTS), dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4")])
    for index, axis in enumerate("xyz"):
        vertices[axis] = POINTS[:, index]
    stream = io.BytesIO()
    PlyData([PlyElement.describe(vertices, "vertex")], byte_order=">").write(stream)
    assert b"format binary_big_endian" in stream.getvalue()[:100]
    np.testing.assert_array_equal(read_cloud(stream.getvalue(), "source", LIMIT), POINTS)


def test_declared_point_counts_above_the_limit_are_refused_before_decoding():
    """Headers that claim huge clouds in a few bytes must not make the service allocate them."""
    fake_npy = npy_bytes(np.zeros((2000, 3), np.float32))[:200]  # header says 2000 rows; body cut short
    fake_ply = b"ply\nformat ascii 1.0\nelement vertex 99999999999\nproperty float x\nproperty float y\n"
    fake_ply += b"property float z\nend_header\n0 0 0\n"
    fake_pcd = b"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 99999999\nHEIGHT 1\n"
    fake_pcd += b"POINTS 99999999\nDATA binary\n" + b"\0" * 12
    for data in (fake_npy, fake_ply, fake_pcd):
        with pytest.raises(InvalidInput, match="more than the limit of 1000"):
            read_cloud(data, "source", LIMIT)


def test_compressed_pcd_claiming_more_bytes_than_its_points_is_refused():
    data = bytearray(pcd_bytes(POINTS, Encoding.BINARY_COMPRESSED))
    start = data.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    compressed, _ = struct.unpack("<II", data[start : start + 8])
    data[start : start + 8] = struct.pack("<II", compressed, 2**31)
    with pytest.raises(InvalidInput, match="compressed block claims"):
        read_cloud(bytes(data), "source", LIMIT)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        (ply_bytes(POINTS, text=False)[:-100], "unreadable PLY"),
        (b"ply\nformat ascii 1.0\nelement face 1\nproperty float x\nend_header\n1\n", "no `vertex` element"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float a\nend_header\n1\n", "lack x, y, z"),
        (pcd_bytes(POINTS, Encoding.BINARY)[:-40], "unreadable PCD"),
        (b"VERSION 0.7\nFIELDS a b\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\nPOINTS 1\nDATA ascii\n1 2\n", "lacks x, y, z"),
        (b"VERSION 0.7\nFIELDS x y z\n", "no DATA line"),
        (npy_bytes(POINTS)[:-30], "unreadable NPY"),
    ],
    ids=["ply-truncated", "ply-no-vertex", "ply-no-xyz", "pcd-truncated", "pcd-no-xyz", "pcd-no-data", "npy-truncated"],
)
def test_malformed_files_are_invalid_input(data, message):
    with pytest.raises(InvalidInput, match=message):
        read_cloud(data, "source", LIMIT)


def test_unknown_formats_are_unsupported():
    with pytest.raises(UnsupportedFormat, match="unrecognised file format"):
        read_cloud(b"x y z\n1 2 3\n", "source", LIMIT)
    with pytest.raises(UnsupportedFormat, match="NPZ archive"):
        read_cloud(b"PK\x03\x04rest", "source", LIMIT)


def test_raw_pair_bodies():
    other = POINTS[:40] + 1.0
    stream = io.BytesIO()
    np.savez_compressed(stream, source=POINTS, target=other)
    source, target = read_pair(stream.getvalue(), LIMIT)
    np.testing.assert_array_equal(source, POINTS)
    np.testing.assert_array_equal(target, other)

    source, target = read_pair(npy_bytes(np.stack([POINTS, POINTS + 1.0])), LIMIT)
    np.testing.assert_array_equal(target, POINTS + 1.0)

    with pytest.raises(InvalidInput, match=r"\[2, N, 3\]"):
        read_pair(npy_bytes(POINTS), LIMIT)
    stream = io.BytesIO()
    np.savez(stream, source=POINTS)
    with pytest.raises(InvalidInput, match="no `target` array") as caught:
        read_pair(stream.getvalue(), LIMIT)
    assert caught.value.field == "target"
    with pytest.raises(UnsupportedFormat, match="multipart"):
        read_pair(ply_bytes(POINTS, text=True), LIMIT)


def test_npz_members_larger_than_a_cloud_are_refused_before_decompression():
    stream = io.BytesIO()
    np.savez_compressed(stream, source=np.zeros((5000, 3)), target=POINTS)  # compresses to a few bytes
    with pytest.raises(InvalidInput, match="bytes uncompressed"):
        read_pair(stream.getvalue(), LIMIT)
