"""Hostile files and archives, read without the service around them: zip bombs, damaged archives,
headers that lie about their data. Each is refused with InvalidInput (422) naming the problem,
quickly, and without allocating much more than the file itself (traced with tracemalloc, which
sees numpy's and every Python allocation)."""

import io
import struct
import time
import tracemalloc
import zipfile
import zlib

import numpy as np
import pytest
from plyfile import PlyData, PlyElement
from pypcd4 import Encoding, PointCloud

from service.formats import MAX_ARCHIVE_MEMBERS, read_cloud, read_pair
from service.validation import InvalidInput

POINTS = (np.random.default_rng(1).integers(-40, 40, size=(600, 3)) / 8.0).astype(np.float32)
LIMIT = 500_000  # the service's default point limit per cloud


def npy_bytes(array: np.ndarray) -> bytes:
    stream = io.BytesIO()
    np.save(stream, array)
    return stream.getvalue()


def npy_header(descr: str, shape: tuple[int, ...]) -> bytes:
    """A version 1.0 NPY header declaring any dtype and shape (the data after it is up to the caller)."""
    text = repr({"descr": descr, "fortran_order": False, "shape": shape}).encode()
    text += b" " * (63 - (10 + len(text)) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(text)) + text


def zip_archive(members: list[dict]) -> bytes:
    """A zip written by hand, so that each field can lie: name, data (as stored), method, crc,
    size (declared uncompressed size) and flags."""
    local, directory, offset = [], [], 0
    for member in members:
        name = member["name"].encode()
        fields = (
            20,
            member.get("flags", 0),
            member.get("method", 0),
            0,
            0,
            member.get("crc", zlib.crc32(member.get("plain", member["data"]))),
            len(member["data"]),
            member.get("size", len(member.get("plain", member["data"]))),
            len(name),
            0,
        )
        local.append(struct.pack("<4s5H3L2H", b"PK\x03\x04", *fields) + name + member["data"])
        directory.append(struct.pack("<4sH5H3L5H2L", b"PK\x01\x02", 20, *fields, 0, 0, 0, 0, offset) + name)
        offset += len(local[-1])
    directory_bytes = b"".join(directory)
    end = struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, len(members), len(members), len(directory_bytes), offset, 0)
    return b"".join(local) + directory_bytes + end


def deflated(data: bytes) -> bytes:
    squeezer = zlib.compressobj(9, zlib.DEFLATED, -15)
    return squeezer.compress(data) + squeezer.flush()


def deflate_bomb(megabytes: int) -> bytes:
    """A raw deflate stream of `megabytes` MiB of zeros in about a kilobyte per MiB: one flushed
    segment (which refers to nothing before it) repeated, then an empty final block."""
    squeezer = zlib.compressobj(9, zlib.DEFLATED, -15)
    segment = squeezer.compress(bytes(1 << 20)) + squeezer.flush(zlib.Z_FULL_FLUSH)
    return segment * megabytes + zlib.compressobj(9, zlib.DEFLATED, -15).flush()


def refused(read, *args, match: str, max_seconds: float = 2.0, max_megabytes: float = 16.0) -> InvalidInput:
    """Calls read(*args), which must raise InvalidInput matching `match` within the time and memory given."""
    tracemalloc.start()
    started = time.perf_counter()
    try:
        with pytest.raises(InvalidInput, match=match) as caught:
            read(*args)
        seconds = time.perf_counter() - started
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert seconds < max_seconds, f"took {seconds:.1f} s"
    assert peak < max_megabytes * 2**20, f"allocated {peak / 2**20:.1f} MiB"
    assert len(str(caught.value)) < 600  # a few names at most, whatever the file holds
    return caught.value


def npz_of(source: bytes, target: bytes, **overrides) -> bytes:
    members = [{"name": "source.npy", "data": source}, {"name": "target.npy", "data": target}]
    members[0].update(overrides)
    return zip_archive(members)


def test_the_hand_made_archive_reads_like_numpys():
    data = npz_of(npy_bytes(POINTS), npy_bytes(POINTS + 1))
    source, target = read_pair(data, LIMIT)
    np.testing.assert_array_equal(target, POINTS + 1)
    plain = npy_bytes(POINTS)
    source, _ = read_pair(npz_of(deflated(plain), plain, method=zipfile.ZIP_DEFLATED, plain=plain), LIMIT)
    np.testing.assert_array_equal(source, POINTS)


# ---------------------------------------------------------------- row 1: NPZ bombs


def test_an_npz_member_that_inflates_far_past_its_declared_size_is_refused_in_bounded_memory():
    bomb = deflate_bomb(1024)  # 1 GiB of zeros in ~1 MB, declared as 14 kB
    header = npy_header("<f8", (500, 3))
    data = npz_of(header + bomb, npy_bytes(POINTS), method=zipfile.ZIP_DEFLATED, size=14_000, crc=0)
    assert len(data) < 2 * 2**20
    refused(read_pair, data, LIMIT, match="source: .*(ends after|CRC)", max_megabytes=8)


def test_an_npz_member_declared_larger_than_a_cloud_is_refused_before_inflating():
    data = npz_of(deflate_bomb(64), npy_bytes(POINTS), method=zipfile.ZIP_DEFLATED, size=2**30)
    refused(read_pair, data, LIMIT, match="bytes uncompressed, more than a cloud")


@pytest.mark.parametrize(("method", "name"), [(zipfile.ZIP_BZIP2, "bzip2"), (zipfile.ZIP_LZMA, "lzma"), (99, "99")])
def test_compression_methods_other_than_stored_and_deflate_are_refused(method, name):
    """bzip2 inflates a whole block per read, so its bombs could not be bounded chunk by chunk."""
    plain = npy_bytes(POINTS)
    data = npz_of(b"\x00garbage" * 100, plain, method=method, plain=plain)
    refused(read_pair, data, LIMIT, match=f"compression method {method}")


# ---------------------------------------------------------------- row 8: damaged archives


def damaged_archives() -> dict[str, bytes]:
    plain = npy_bytes(POINTS)
    good = npz_of(deflated(plain), plain, method=zipfile.ZIP_DEFLATED, plain=plain)
    corrupt_deflate = bytearray(deflated(plain))
    corrupt_deflate[40:60] = b"\xff" * 20
    return {
        "bad crc": npz_of(plain, plain, crc=12345),
        "corrupt deflate": npz_of(bytes(corrupt_deflate), plain, method=zipfile.ZIP_DEFLATED, plain=plain),
        "encrypted flag": npz_of(plain, plain, flags=0x1),
        "method 99": npz_of(plain, plain, method=99),
        "lzma garbage": npz_of(b"\x09\x14" + bytes(200), plain, method=zipfile.ZIP_LZMA, plain=plain),
        "truncated": good[: len(good) // 2],
        "no end record": good[:-22],
        "garbage directory": good[: len(good) - 60] + bytes(38) + good[-22:],
    }


@pytest.mark.parametrize("case", sorted(damaged_archives()))
def test_damaged_archives_are_invalid_input_naming_the_archive_problem(case):
    error = refused(read_pair, damaged_archives()[case], LIMIT, match="NPZ|compression method")
    assert error.field in ("body", "source", "target")


# ---------------------------------------------------------------- row 12: archives with very many members


def test_an_archive_listing_very_many_members_is_refused_from_its_end_record():
    members = [{"name": f"m{index:07d}.npy", "data": b""} for index in range(60_000)]
    data = zip_archive([{"name": "source.npy", "data": npy_bytes(POINTS)}, *members])
    error = refused(read_pair, data, LIMIT, match="lists 60001 members", max_megabytes=24)
    assert "m0000" not in str(error)


def test_an_archive_hiding_members_behind_a_small_declared_count_is_refused():
    """zipfile reads the whole directory whatever the count says, so its size is bounded too."""
    members = [{"name": f"m{index:07d}.npy", "data": b""} for index in range(20_000)]
    data = bytearray(zip_archive(members))
    data[-12:-10] = struct.pack("<H", 2)  # entries on this disk and in total, as the end record gives them
    data[-14:-12] = struct.pack("<H", 2)
    refused(read_pair, bytes(data), LIMIT, match="directory")


def test_missing_arrays_name_only_a_few_members():
    members = [{"name": f"cloud{index}.npy", "data": b""} for index in range(MAX_ARCHIVE_MEMBERS)]
    error = refused(read_pair, zip_archive(members), LIMIT, match="no `source` array")
    assert "and 11 more" in str(error)


# ---------------------------------------------------------------- row 9: NPY types


@pytest.mark.parametrize("descr", ["|V1000000000", "<U2500000", "|S1000000000", "|b1", "<c16", "<f16"])
def test_npy_types_other_than_plain_numbers_are_refused_from_the_header(descr):
    data = npy_header(descr, (500_000, 3)) + bytes(64)
    refused(read_cloud, data, "source", LIMIT, match="are not accepted|not understood|unreadable NPY header")
    pair = npy_header(descr, (2, 500_000, 3)) + bytes(64)
    refused(read_pair, pair, LIMIT, match="are not accepted|not understood|unreadable NPY header")


def test_npy_data_must_match_its_header():
    refused(read_cloud, npy_bytes(POINTS) + b"\0" * 12, "source", LIMIT, match="more than the 7200 data bytes")
    refused(read_cloud, npy_bytes(POINTS)[:-12], "source", LIMIT, match="ends after 7188 of the 7200")


def test_fortran_ordered_npy_reads_as_saved():
    array = np.asfortranarray(POINTS.astype(np.float64))
    np.testing.assert_array_equal(read_cloud(npy_bytes(array), "source", LIMIT), POINTS)


# ---------------------------------------------------------------- rows 2, 3, 15: PCD


def pcd_head(fields: str, sizes: str, types: str, counts: str, points: int, encoding: str) -> bytes:
    return (
        f"# .PCD v0.7\nVERSION 0.7\nFIELDS {fields}\nSIZE {sizes}\nTYPE {types}\nCOUNT {counts}\n"
        f"WIDTH {points}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {points}\nDATA {encoding}\n"
    ).encode()


def test_a_compressed_pcd_whose_counts_make_a_huge_block_is_refused_before_decompressing():
    head = pcd_head("x y z w", "4 4 4 4", "F F F F", "1 1 1 500", 500_000, "binary_compressed")
    block_bytes = 500_000 * (12 + 2000)
    data = head + struct.pack("<II", 11_000_000, block_bytes) + bytes(11_000_000)
    refused(read_cloud, data, "source", LIMIT, match="declares 500000 points of 2012 bytes, more than the limit")


def test_a_compressed_block_must_claim_exactly_what_its_points_take():
    data = bytearray(pcd_via_pypcd4(Encoding.BINARY_COMPRESSED))
    start = data.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    compressed, _ = struct.unpack("<II", data[start : start + 8])
    data[start : start + 8] = struct.pack("<II", compressed, 2**31)
    refused(read_cloud, bytes(data), "source", LIMIT, match="compressed block claims 2147483648 bytes")


def pcd_via_pypcd4(encoding: Encoding) -> bytes:
    stream = io.BytesIO()
    PointCloud.from_xyz_points(POINTS).save(stream, encoding=encoding)
    return stream.getvalue()


def test_a_header_line_that_other_readers_skip_is_refused_not_read_differently():
    """A lower-case `data` line: one reader stops there, another reads on to the real DATA line."""
    head = pcd_head("x y z", "4 4 4", "F F F", "1 1 1", 40, "ascii").replace(b"DATA ascii\n", b"data ascii\n")
    head += b"POINTS 20000000\nDATA binary_compressed\n"
    data = head + struct.pack("<II", 100, 20_000_000 * 12) + bytes(100)
    refused(read_cloud, data, "source", LIMIT, match="'data ascii' is not one of the keys")


def test_a_pcd_key_given_twice_is_refused():
    head = pcd_head("x y z", "4 4 4", "F F F", "1 1 1", 40, "ascii").replace(b"DATA", b"POINTS 20000000\nDATA")
    refused(read_cloud, head + b"0 0 0\n" * 40, "source", LIMIT, match="two POINTS lines")


@pytest.mark.parametrize("encoding", ["ascii", "binary"])
def test_pcd_points_must_match_its_rows(encoding):
    head = pcd_head("x y z", "4 4 4", "F F F", "1 1 1", 40, encoding)
    if encoding == "ascii":
        body = "".join(f"{x} {y} {z}\n" for x, y, z in POINTS).encode()
        refused(read_cloud, head + body, "source", LIMIT, match="more data than its header declares")
        refused(read_cloud, head + body[:200], "source", LIMIT, match="ends after|rows where its header declares")
    else:
        body = POINTS.astype("<f4").tobytes()
        refused(read_cloud, head + body, "source", LIMIT, match="7200 data bytes where its header declares")
        refused(read_cloud, head + body[:100], "source", LIMIT, match="100 data bytes where")


def test_pcd_points_must_match_width_and_height():
    head = pcd_head("x y z", "4 4 4", "F F F", "1 1 1", 600, "binary").replace(b"WIDTH 600", b"WIDTH 40")
    refused(read_cloud, head + POINTS.tobytes(), "source", LIMIT, match="WIDTH x HEIGHT is 40")


@pytest.mark.parametrize("encoding", [Encoding.ASCII, Encoding.BINARY, Encoding.BINARY_COMPRESSED])
def test_pcd_with_extra_fields_reads_only_xyz(encoding):
    cloud = PointCloud.from_xyzi_points(np.hstack([POINTS, np.ones((len(POINTS), 1), np.float32)]))
    stream = io.BytesIO()
    cloud.save(stream, encoding=encoding)
    np.testing.assert_array_equal(read_cloud(stream.getvalue(), "source", LIMIT), POINTS)


# ---------------------------------------------------------------- rows 5, 15: PLY


def ply_bytes(points: np.ndarray, text: bool, faces: int = 0) -> bytes:
    vertices = np.zeros(len(points), dtype=[("x", "f4"), ("y", "f4"), ("z", "f4")])
    for index, axis in enumerate("xyz"):
        vertices[axis] = points[:, index]
    elements = [PlyElement.describe(vertices, "vertex")]
    if faces:
        face = np.zeros(faces, dtype=[("vertex_indices", "i4", (3,))])
        face["vertex_indices"] = np.arange(faces * 3).reshape(faces, 3) % len(points)
        elements.append(PlyElement.describe(face, "face"))
    stream = io.BytesIO()
    PlyData(elements, text=text).write(stream)
    return stream.getvalue()


@pytest.mark.parametrize("text", [True, False], ids=["ascii", "binary"])
def test_ply_declaring_fewer_vertices_than_it_holds_is_refused(text):
    data = ply_bytes(POINTS, text).replace(b"element vertex 600", b"element vertex 500")
    refused(read_cloud, data, "source", LIMIT, match="more data than its header declares \\(500 vertices\\)")


@pytest.mark.parametrize("text", [True, False], ids=["ascii", "binary"])
def test_ply_meshes_read_their_vertices(text):
    np.testing.assert_array_equal(read_cloud(ply_bytes(POINTS, text, faces=10), "source", LIMIT), POINTS)


def test_ascii_ply_rows_after_the_vertices_must_match_the_other_elements():
    data = ply_bytes(POINTS, True, faces=10).replace(b"element face 10", b"element face 3")
    refused(read_cloud, data, "source", LIMIT, match="holds 10 rows after its vertices where its header declares 3")


def test_a_ply_header_of_endless_comments_is_refused_at_once():
    data = b"ply\nformat ascii 1.0\n" + b"comment padding padding padding padding\n" * 750_000  # 30 MB
    refused(read_cloud, data, "source", LIMIT, match="no end_header line in its first 65536 bytes", max_seconds=0.5)


def test_a_huge_element_count_before_the_vertices_is_refused_without_allocating():
    data = b"ply\nformat binary_little_endian 1.0\nelement junk 4000000000\nproperty double a\n"
    data += b"element vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n" + bytes(36)
    refused(read_cloud, data, "source", LIMIT, match="element 'junk' declares 4000000000 rows")
