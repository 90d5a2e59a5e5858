"""Point clouds from uploaded files: PLY (plyfile), PCD (pypcd4) and NPY/NPZ (numpy, never pickle).

Formats are recognised by their first bytes, not by file names. Each reader checks the point
count a file declares against a limit before decoding it, so a small upload cannot make the
service allocate gigabytes.
"""

import io
import re
import struct
import zipfile
from pathlib import Path

import numpy as np

from service.validation import InvalidInput, as_points

FORMATS = ("ply", "pcd", "npy")
NPY_MAGIC = b"\x93NUMPY"
ZIP_MAGIC = b"PK\x03\x04"


class UnsupportedFormat(Exception):
    """Content that is none of the accepted formats (answered with 415)."""


def detect_format(data: bytes) -> str | None:
    """ "ply", "pcd", "npy" or "npz" from a file's first bytes, or None."""
    if data.startswith(b"ply") and data[3:4] in (b"\n", b"\r"):
        return "ply"
    if data.startswith(NPY_MAGIC):
        return "npy"
    if data.startswith(ZIP_MAGIC):
        return "npz"
    head = data[:512].lstrip()
    if head.startswith((b"# .PCD", b"VERSION", b"FIELDS")):
        return "pcd"
    return None


def read_cloud(data: bytes, field: str, max_cloud_points: int) -> np.ndarray:
    """One cloud [N, 3] float64 from the bytes of a PLY, PCD or NPY file."""
    kind = detect_format(data)
    if kind == "ply":
        points = read_ply(data, field, max_cloud_points)
    elif kind == "pcd":
        points = read_pcd(data, field, max_cloud_points)
    elif kind == "npy":
        points = read_npy(data, field, max_cloud_points)
    elif kind == "npz":
        raise UnsupportedFormat(f"{field}: an NPZ archive holds several arrays; upload one cloud as PLY, PCD or NPY")
    else:
        raise UnsupportedFormat(f"{field}: unrecognised file format; upload PLY, PCD or NPY (.npy, no pickle)")
    return as_points(points, field)


def read_cloud_file(path: str | Path, max_cloud_points: int = 10_000_000) -> np.ndarray:
    """A cloud from a file on disk (used by the command-line client)."""
    return read_cloud(Path(path).read_bytes(), str(path), max_cloud_points)


def _too_many(field: str, count: int, max_cloud_points: int) -> InvalidInput:
    return InvalidInput(field, f"the file declares {count} points, more than the limit of {max_cloud_points}")


# ---------------------------------------------------------------- PLY


def read_ply(data: bytes, field: str, max_cloud_points: int) -> np.ndarray:
    from plyfile import PlyData

    header_end = data.find(b"end_header")
    if header_end < 0:
        raise InvalidInput(field, "PLY header has no end_header line")
    match = re.search(rb"^element\s+vertex\s+(\d+)", data[:header_end], flags=re.MULTILINE)
    if match is None:
        raise InvalidInput(field, "PLY file has no `vertex` element")
    if int(match.group(1)) > max_cloud_points:
        raise _too_many(field, int(match.group(1)), max_cloud_points)
    try:
        vertices = PlyData.read(io.BytesIO(data))["vertex"]
        names = {prop.name for prop in vertices.properties}
        if not {"x", "y", "z"} <= names:
            raise InvalidInput(field, f"PLY vertices lack x, y, z properties (they have {sorted(names)})")
        return np.stack([np.asarray(vertices[axis], dtype=np.float64) for axis in "xyz"], axis=1)
    except InvalidInput:
        raise
    except Exception as error:  # plyfile raises several types for truncated or malformed files
        raise InvalidInput(field, f"unreadable PLY file: {error}") from None


# ---------------------------------------------------------------- PCD


def _pcd_header(data: bytes, field: str) -> tuple[dict[str, list[str]], int]:
    """The header's keys (FIELDS, SIZE, ...) and the offset where the point data starts."""
    header: dict[str, list[str]] = {}
    offset = 0
    while offset < len(data):
        end = data.find(b"\n", offset)
        end = len(data) if end < 0 else end + 1
        line = data[offset:end].decode("ascii", errors="replace").strip()
        offset = end
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            return header, offset
        if offset > 4096:
            break
    raise InvalidInput(field, "PCD header has no DATA line")


def read_pcd(data: bytes, field: str, max_cloud_points: int) -> np.ndarray:
    from pypcd4 import PointCloud

    header, data_start = _pcd_header(data, field)
    names = header.get("FIELDS", [])
    if not {"x", "y", "z"} <= set(names):
        raise InvalidInput(field, f"PCD file lacks x, y, z fields (it has {names})")
    try:
        count = int((header.get("POINTS") or ["-1"])[0])
        if count < 0:
            count = int(header["WIDTH"][0]) * int((header.get("HEIGHT") or ["1"])[0])
        row_bytes = sum(
            int(size) * int(n) for size, n in zip(header["SIZE"], header.get("COUNT", ["1"] * len(names)), strict=False)
        )
    except (KeyError, ValueError, IndexError):
        raise InvalidInput(field, "PCD header lacks a valid POINTS, WIDTH/HEIGHT, SIZE or COUNT line") from None
    if count > max_cloud_points:
        raise _too_many(field, count, max_cloud_points)
    encoding = (header["DATA"] or [""])[0].lower()
    if encoding not in ("ascii", "binary", "binary_compressed"):
        raise UnsupportedFormat(
            f"{field}: PCD encoding {encoding!r} is not supported (ascii, binary, binary_compressed)"
        )
    if encoding == "binary_compressed":
        if len(data) < data_start + 8:
            raise InvalidInput(field, "PCD file ends before its compressed data")
        _, uncompressed = struct.unpack("<II", data[data_start : data_start + 8])
        if uncompressed > count * row_bytes:  # would make the decompressor allocate more than the points need
            raise InvalidInput(field, f"PCD compressed block claims {uncompressed} bytes for {count} points")
    try:
        cloud = PointCloud.from_fileobj(io.BytesIO(data))
        return np.asarray(cloud.numpy(("x", "y", "z")), dtype=np.float64)
    except Exception as error:  # pypcd4 raises ValueError, RuntimeError, pydantic errors, lzf errors...
        raise InvalidInput(field, f"unreadable PCD file: {error}") from None


# ---------------------------------------------------------------- NPY / NPZ


def _npy_header(stream: io.BytesIO, field: str) -> tuple[tuple[int, ...], np.dtype]:
    try:
        version = np.lib.format.read_magic(stream)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(stream)
        else:
            shape, _, dtype = np.lib.format.read_array_header_2_0(stream)
    except ValueError as error:
        raise InvalidInput(field, f"unreadable NPY header: {error}") from None
    return shape, dtype


def read_npy(data: bytes, field: str, max_cloud_points: int) -> np.ndarray:
    """An [N, 3] numeric array; object arrays are refused (loading them would need pickle)."""
    shape, dtype = _npy_header(io.BytesIO(data), field)
    if dtype.hasobject:
        raise InvalidInput(field, "NPY object arrays are not accepted (they need pickle); save a numeric N x 3 array")
    if len(shape) != 2 or shape[1] != 3:
        raise InvalidInput(field, f"NPY array must be N x 3, got shape {list(shape)}")
    if shape[0] > max_cloud_points:
        raise _too_many(field, shape[0], max_cloud_points)
    try:
        return np.load(io.BytesIO(data), allow_pickle=False)
    except ValueError as error:
        raise InvalidInput(field, f"unreadable NPY file: {error}") from None


def read_pair(data: bytes, max_cloud_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Source and target from one raw body: NPY of shape [2, N, 3], or NPZ with arrays `source` and `target`."""
    kind = detect_format(data)
    if kind == "npy":
        shape, dtype = _npy_header(io.BytesIO(data), "body")
        if dtype.hasobject:
            raise InvalidInput("body", "NPY object arrays are not accepted (they need pickle); save a numeric array")
        if len(shape) != 3 or shape[0] != 2 or shape[2] != 3:
            raise InvalidInput(
                "body", f"a raw NPY body must be a numeric [2, N, 3] array (source, target), got {list(shape)}"
            )
        if shape[1] > max_cloud_points:
            raise _too_many("body", shape[1], max_cloud_points)
        try:
            pair = np.load(io.BytesIO(data), allow_pickle=False)
        except ValueError as error:
            raise InvalidInput("body", f"unreadable NPY body: {error}") from None
        return as_points(pair[0], "source"), as_points(pair[1], "target")
    if kind == "npz":
        return _read_npz_pair(data, max_cloud_points)
    if kind in ("ply", "pcd"):
        raise UnsupportedFormat(
            f"body: a raw {kind.upper()} body holds one cloud; send source and target as multipart/form-data file parts"
        )
    raise UnsupportedFormat("body: unrecognised format; send NPY ([2, N, 3]) or NPZ (`source`, `target`) bytes")


def _read_npz_pair(data: bytes, max_cloud_points: int) -> tuple[np.ndarray, np.ndarray]:
    limit = max_cloud_points * 3 * 8 + 4096  # the largest acceptable float64 cloud plus its NPY header
    try:
        archive = zipfile.ZipFile(io.BytesIO(data))
        sizes = {info.filename: info.file_size for info in archive.infolist()}
    except zipfile.BadZipFile as error:
        raise InvalidInput("body", f"unreadable NPZ archive: {error}") from None
    clouds = []
    for name in ("source", "target"):
        size = sizes.get(f"{name}.npy")
        if size is None:
            raise InvalidInput(name, f"the NPZ archive has no `{name}` array (it has {sorted(sizes)})")
        if size > limit:
            raise InvalidInput(
                name, f"the NPZ array is {size} bytes uncompressed, more than a cloud of {max_cloud_points} points"
            )
        clouds.append(read_npy(archive.read(f"{name}.npy"), name, max_cloud_points))
    return as_points(clouds[0], "source"), as_points(clouds[1], "target")


# ---------------------------------------------------------------- writing (client side)


def write_ply(path: str | Path, points: np.ndarray) -> None:
    """A binary little-endian PLY with float32 x, y, z vertices."""
    from plyfile import PlyData, PlyElement

    vertices = np.empty(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    for index, axis in enumerate("xyz"):
        vertices[axis] = points[:, index]
    PlyData([PlyElement.describe(vertices, "vertex")]).write(str(path))
