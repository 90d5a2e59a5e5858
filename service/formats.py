"""Point clouds from uploaded files: PLY, PCD and NPY/NPZ, decoded here with numpy (never pickle).

Formats are recognised by their first bytes, not by file names. Each reader parses its file's
header once, checks what it declares (point count, field sizes, data length) against the limits
and against the data actually present, and only then allocates: a small upload cannot make the
service allocate more than a few times its own size, and a file whose header and data disagree
is refused rather than read in part.
"""

import io
import math
import re
import struct
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from service.validation import InvalidInput, as_points

NPY_MAGIC = b"\x93NUMPY"
ZIP_MAGIC = b"PK\x03\x04"
MAX_HEADER_BYTES = 64 * 1024  # PLY and PCD headers; real ones are a few hundred bytes
DEFAULT_MAX_DECODED_BYTES = 64 * 1024 * 1024  # what one file may decode to, unless the caller says
MAX_ARCHIVE_MEMBERS = 16
MAX_ARCHIVE_DIRECTORY_BYTES = 64 * 1024
READ_CHUNK_BYTES = 1 << 20
SHOWN_NAMES = 5  # members named in an error, so that its size stays small whatever the archive holds
NON_SPACE = re.compile(rb"\S")
# What zipfile raises for damaged archives: bad records or CRCs, corrupt deflate data, truncation,
# and the features it cannot read (encryption, patched data).
ARCHIVE_ERRORS = (
    zipfile.BadZipFile,
    zipfile.LargeZipFile,
    zlib.error,
    EOFError,
    ValueError,
    struct.error,
    OSError,
    NotImplementedError,
    RuntimeError,
)


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


def read_cloud(
    data: bytes, field: str, max_cloud_points: int, max_decoded_bytes: int = DEFAULT_MAX_DECODED_BYTES
) -> np.ndarray:
    """One cloud [N, 3] float64 from the bytes of a PLY, PCD or NPY file.

    `max_decoded_bytes` bounds what a compressed file may expand to (PCD binary_compressed).
    """
    kind = detect_format(data)
    if kind == "ply":
        points = read_ply(data, field, max_cloud_points)
    elif kind == "pcd":
        points = read_pcd(data, field, max_cloud_points, max_decoded_bytes)
    elif kind == "npy":
        points = read_npy(data, field, max_cloud_points)
    elif kind == "npz":
        raise UnsupportedFormat(f"{field}: an NPZ archive holds several arrays; upload one cloud as PLY, PCD or NPY")
    else:
        raise UnsupportedFormat(f"{field}: unrecognised file format; upload PLY, PCD or NPY (.npy, no pickle)")
    return as_points(points, field)


def read_cloud_file(path: str | Path, max_cloud_points: int = 10_000_000) -> np.ndarray:
    """A cloud from a file on disk (used by the command-line client)."""
    data = Path(path).read_bytes()
    return read_cloud(
        data, str(path), max_cloud_points, max_decoded_bytes=max(DEFAULT_MAX_DECODED_BYTES, 8 * len(data))
    )


def _too_many(field: str, count: int, max_cloud_points: int) -> InvalidInput:
    return InvalidInput(field, f"the file declares {count} points, more than the limit of {max_cloud_points}")


def _count(text: str, field: str, what: str) -> int:
    if not text.isdigit():
        raise InvalidInput(field, f"{what} must be a non-negative whole number, got {text[:40]!r}")
    return int(text)


def _line_end(data: bytes, start: int, rows: int, field: str, what: str) -> int:
    """The offset just past the `rows`-th line that starts at `start` (the end of the data at the last line)."""
    position = start
    for row in range(rows):
        end = data.find(b"\n", position)
        if end < 0:
            if row == rows - 1 and NON_SPACE.search(data, position):
                return len(data)
            raise InvalidInput(field, f"the file ends after {row} of the {rows} {what} rows its header declares")
        position = end + 1
    return position


def _text_rows(data: bytes, start: int, rows: int, columns: int, keep: list[int], field: str, what: str):
    """`rows` whitespace-separated lines of `columns` numbers from `start`: (the `keep` columns as float64, end)."""
    end = _line_end(data, start, rows, field, what)
    block = data[start:end]
    first = block.split(b"\n", 1)[0].split()
    if rows and len(first) != columns:
        raise InvalidInput(field, f"{what} row 0 has {len(first)} values; the header declares {columns}")
    try:
        values = np.loadtxt(io.BytesIO(block), dtype=np.float64, usecols=keep, ndmin=2, comments=None)
    except ValueError as error:
        raise InvalidInput(field, f"unreadable {what} rows: {error}") from None
    if len(values) != rows:  # blank lines are skipped by the parser, so they show up here
        raise InvalidInput(field, f"holds {len(values)} {what} rows where its header declares {rows}")
    return values.reshape(rows, len(keep)), end


def _check_nothing_after(data: bytes, end: int, field: str, declared: str, text: bool) -> None:
    extra = NON_SPACE.search(data, end) is not None if text else end < len(data)
    if extra:
        raise InvalidInput(
            field, f"holds more data than its header declares ({declared}); fix the header's count or the data"
        )


# ---------------------------------------------------------------- PLY


PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}
PLY_ORDERS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}


def _header_end(data: bytes, marker: bytes, field: str, kind: str) -> int:
    """The offset after the line starting with the word `marker`, which must come within MAX_HEADER_BYTES."""
    found = re.search(rb"^" + marker + rb"\b[^\n]*(\n|$)", data[:MAX_HEADER_BYTES], flags=re.MULTILINE)
    if found is None:
        if len(data) > MAX_HEADER_BYTES:
            raise InvalidInput(
                field, f"{kind} header has no {marker.decode()} line in its first {MAX_HEADER_BYTES} bytes"
            )
        raise InvalidInput(field, f"{kind} header has no {marker.decode()} line")
    return found.end()


def _ply_header(data: bytes, field: str) -> tuple[str, list[tuple[str, int, list[tuple[str, str | None]]]], int]:
    """(format, [(element, count, [(property, numpy type or None for a list)])], data offset)."""
    data_start = _header_end(data, b"end_header", field, "PLY")
    lines = data[:data_start].decode("ascii", errors="replace").splitlines()
    encoding = None
    elements: list[tuple[str, int, list[tuple[str, str | None]]]] = []
    for line in lines[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format" and len(words) == 3 and encoding is None:
            encoding = words[1]
            if encoding not in PLY_ORDERS:
                raise UnsupportedFormat(f"{field}: PLY format {encoding[:40]!r} is not one of {sorted(PLY_ORDERS)}")
        elif words[0] == "element" and len(words) == 3:
            elements.append((words[1], _count(words[2], field, f"the PLY count of element {words[1]!r}"), []))
        elif words[0] == "property" and elements and len(words) == 3 and words[1] in PLY_TYPES:
            elements[-1][2].append((words[2], PLY_TYPES[words[1]]))
        elif words[0] == "property" and elements and len(words) == 5 and words[1] == "list":
            if words[2] not in PLY_TYPES or words[3] not in PLY_TYPES:
                raise InvalidInput(field, f"PLY header line {line[:80]!r} has an unknown list type")
            elements[-1][2].append((words[4], None))
        else:
            raise InvalidInput(field, f"PLY header line {line[:80]!r} is not valid PLY")
    if encoding is None:
        raise InvalidInput(field, "PLY header has no `format` line")
    return encoding, elements, data_start


def read_ply(data: bytes, field: str, max_cloud_points: int) -> np.ndarray:
    encoding, elements, position = _ply_header(data, field)
    names = [name for name, _, _ in elements]
    if "vertex" not in names:
        raise InvalidInput(field, f"PLY file has no `vertex` element (it has {names[:SHOWN_NAMES]})")
    order = PLY_ORDERS[encoding]
    vertex_index = names.index("vertex")
    _, count, properties = elements[vertex_index]
    if count > max_cloud_points:
        raise _too_many(field, count, max_cloud_points)
    property_names = [name for name, _ in properties]
    if not {"x", "y", "z"} <= set(property_names):
        raise InvalidInput(field, f"PLY vertices lack x, y, z properties (they have {property_names[:8]})")
    for name, element_count, element_properties in elements[: vertex_index + 1]:
        if any(kind is None for _, kind in element_properties):
            raise InvalidInput(
                field,
                f"PLY element {name!r} has list properties; only a `vertex` element of plain properties, "
                "before any list element (faces), is read",
            )
        if order is None:
            if name != "vertex":
                position = _line_end(data, position, element_count, field, name)
            continue
        row = np.dtype([(f"p{index}", order + kind) for index, (_, kind) in enumerate(element_properties)])
        size = element_count * row.itemsize
        if len(data) - position < size:
            raise InvalidInput(
                field,
                f"unreadable PLY file: element {name!r} declares {element_count} rows ({size} bytes) but "
                f"{len(data) - position} bytes follow",
            )
        if name == "vertex":
            rows = np.frombuffer(data, dtype=row, count=element_count, offset=position)
            points = np.stack([rows[f"p{property_names.index(axis)}"].astype(np.float64) for axis in "xyz"], axis=1)
        position += size
    if order is None:
        keep = [property_names.index(axis) for axis in "xyz"]
        points, position = _text_rows(data, position, count, len(properties), keep, field, "PLY vertex")
    rest = elements[vertex_index + 1 :]
    declared = f"{count} vertices"
    if not rest:
        _check_nothing_after(data, position, field, declared, text=order is None)
    elif order is None:  # one line per row, whatever the element
        declared_rows = sum(element_count for _, element_count, _ in rest)
        end = len(data)
        while end > position and data[end - 1 : end].isspace():
            end -= 1
        lines = data.count(b"\n", position, end) + (1 if end > position else 0)
        if lines != declared_rows:
            raise InvalidInput(
                field, f"holds {lines} rows after its vertices where its header declares {declared_rows}"
            )
    return points


# ---------------------------------------------------------------- PCD


PCD_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS", "DATA")
PCD_TYPES = {("F", 2): "f2", ("F", 4): "f4", ("F", 8): "f8"} | {
    (kind, size): f"{kind.lower()}{size}" for kind in "IU" for size in (1, 2, 4, 8)
}


def _pcd_header(data: bytes, field: str) -> tuple[dict[str, list[str]], int]:
    """The header's keys (FIELDS, SIZE, ...) and the offset where the point data starts."""
    data_start = _header_end(data, b"DATA", field, "PCD")
    header: dict[str, list[str]] = {}
    for line in data[:data_start].decode("ascii", errors="replace").splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        if key not in PCD_KEYS:
            raise InvalidInput(field, f"PCD header line {line[:80]!r} is not one of the keys {', '.join(PCD_KEYS)}")
        if key in header:
            raise InvalidInput(field, f"PCD header has two {key} lines; give each key once")
        header[key] = values
    return header, data_start


def _pcd_layout(header: dict[str, list[str]], field: str) -> tuple[list[str], list[np.dtype], list[int], int]:
    """(field names, numpy type per field, values per field, points), checked against each other."""
    names = header.get("FIELDS", [])
    if not {"x", "y", "z"} <= set(names):
        raise InvalidInput(field, f"PCD file lacks x, y, z fields (it has {names[:8]})")
    sizes = header.get("SIZE", [])
    kinds = header.get("TYPE", [])
    counts = header.get("COUNT", ["1"] * len(names))
    if not len(sizes) == len(kinds) == len(counts) == len(names):
        raise InvalidInput(
            field,
            f"PCD header lists {len(names)} FIELDS but {len(sizes)} SIZE, {len(kinds)} TYPE and {len(counts)} COUNT "
            "values; give one of each per field",
        )
    types = []
    for name, size, kind in zip(names, sizes, kinds, strict=True):
        numpy_type = PCD_TYPES.get((kind, int(size) if size.isdigit() else -1))
        if numpy_type is None:
            raise InvalidInput(
                field, f"PCD field {name!r} has TYPE {kind[:8]!r} with SIZE {size[:8]!r}, not a number type"
            )
        types.append(np.dtype("<" + numpy_type))
    per_field = [
        _count(count, field, f"PCD COUNT of field {name!r}") for name, count in zip(names, counts, strict=True)
    ]
    for axis in "xyz":
        if names.count(axis) != 1 or per_field[names.index(axis)] != 1:
            raise InvalidInput(field, f"PCD field {axis!r} must appear once, with COUNT 1")
    width = _count((header.get("WIDTH") or ["-"])[0], field, "PCD WIDTH")
    height = _count((header.get("HEIGHT") or ["1"])[0], field, "PCD HEIGHT")
    points = _count((header.get("POINTS") or [str(width * height)])[0], field, "PCD POINTS")
    if points != width * height:
        raise InvalidInput(field, f"PCD POINTS is {points} but WIDTH x HEIGHT is {width * height}; they must agree")
    return names, types, per_field, points


def read_pcd(
    data: bytes, field: str, max_cloud_points: int, max_decoded_bytes: int = DEFAULT_MAX_DECODED_BYTES
) -> np.ndarray:
    header, position = _pcd_header(data, field)
    names, types, per_field, count = _pcd_layout(header, field)
    if count > max_cloud_points:
        raise _too_many(field, count, max_cloud_points)
    encoding = (header["DATA"] or [""])[0]
    if encoding not in ("ascii", "binary", "binary_compressed"):
        raise UnsupportedFormat(
            f"{field}: PCD encoding {encoding[:40]!r} is not supported (ascii, binary, binary_compressed)"
        )
    row_bytes = sum(kind.itemsize * values for kind, values in zip(types, per_field, strict=True))
    block_bytes = count * row_bytes
    if block_bytes > max_decoded_bytes:
        raise InvalidInput(
            field,
            f"the PCD header declares {count} points of {row_bytes} bytes, more than the limit of "
            f"{max_decoded_bytes} bytes; drop the fields other than x, y, z",
        )
    columns = [index for index, values in enumerate(per_field) for _ in range(values)]
    keep = [columns.index(names.index(axis)) for axis in "xyz"]
    declared = f"POINTS {count}"
    if encoding == "ascii":
        points, end = _text_rows(data, position, count, len(columns), keep, field, "PCD point")
        _check_nothing_after(data, end, field, declared, text=True)
        return points
    if encoding == "binary":
        if len(data) - position != block_bytes:
            raise InvalidInput(
                field,
                f"unreadable PCD file: {len(data) - position} data bytes where its header declares {declared} x "
                f"{row_bytes} bytes = {block_bytes}",
            )
        row = np.dtype(
            [
                (f"f{index}", (kind, values)) if values > 1 else (f"f{index}", kind)
                for index, (kind, values) in enumerate(zip(types, per_field, strict=True))
            ]
        )
        rows = np.frombuffer(data, dtype=row, count=count, offset=position)
        return np.stack([rows[f"f{names.index(axis)}"].astype(np.float64) for axis in "xyz"], axis=1)
    if len(data) < position + 8:
        raise InvalidInput(field, "unreadable PCD file: it ends before its compressed data")
    compressed, uncompressed = struct.unpack("<II", data[position : position + 8])
    if uncompressed != block_bytes:
        raise InvalidInput(
            field,
            f"PCD compressed block claims {uncompressed} bytes where its header declares {declared} x "
            f"{row_bytes} bytes = {block_bytes}",
        )
    if len(data) - position - 8 != compressed:
        raise InvalidInput(
            field,
            f"unreadable PCD file: its compressed block is {compressed} bytes but {len(data) - position - 8} follow",
        )
    import lzf

    try:
        block = lzf.decompress(data[position + 8 :], block_bytes) if block_bytes else b""
    except ValueError as error:
        raise InvalidInput(field, f"unreadable PCD file: damaged compressed data ({error})") from None
    if block is None or len(block) != block_bytes:
        raise InvalidInput(field, f"unreadable PCD file: its compressed data does not expand to {block_bytes} bytes")
    offsets = np.cumsum([0] + [count * kind.itemsize * values for kind, values in zip(types, per_field, strict=True)])
    axes = []
    for axis in "xyz":  # compressed PCD stores each field's values together
        index = names.index(axis)
        axes.append(np.frombuffer(block, dtype=types[index], count=count, offset=int(offsets[index])))
    return np.stack(axes, axis=1).astype(np.float64)


# ---------------------------------------------------------------- NPY / NPZ


def _npy_array(stream, field: str, check_shape: Callable[[tuple[int, ...]], None], exact_end: bool = True):
    """A numeric array from an NPY stream: header first, checked before anything is allocated,
    then the data read in chunks. `check_shape` raises InvalidInput for shapes the caller refuses."""
    try:
        version = np.lib.format.read_magic(stream)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(stream)
        elif version == (2, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(stream)
        else:
            raise ValueError(f"NPY version {version} is not supported (1.0 or 2.0)")
    except (InvalidInput, zipfile.BadZipFile, zlib.error, EOFError):  # the archive's own damage is named by its reader
        raise
    except Exception as error:  # numpy raises ValueError, SyntaxError or TypeError for a damaged header
        raise InvalidInput(field, f"unreadable NPY header: {str(error)[:200]}") from None
    if dtype.hasobject:
        raise InvalidInput(field, "NPY object arrays are not accepted (they need pickle); save a numeric array")
    if dtype.kind not in "fiu" or dtype.fields is not None or dtype.subdtype is not None or dtype.itemsize > 8:
        raise InvalidInput(
            field, f"NPY arrays of {str(dtype)[:40]} are not accepted; save float32, float64 or integer coordinates"
        )
    if not all(isinstance(size, int) and size >= 0 for size in shape):
        raise InvalidInput(field, f"unreadable NPY header: shape {list(shape)[:8]}")
    check_shape(shape)
    size = math.prod(shape) * dtype.itemsize  # Python integers: no wrap-around
    buffer = bytearray()  # grown as the data arrives, so a header's claim alone allocates nothing
    while len(buffer) < size:
        chunk = stream.read(min(READ_CHUNK_BYTES, size - len(buffer)))
        if not chunk:
            raise InvalidInput(
                field, f"unreadable NPY file: its data ends after {len(buffer)} of the {size} bytes its header declares"
            )
        buffer += chunk
    if exact_end and stream.read(1):
        raise InvalidInput(field, f"unreadable NPY file: it holds more than the {size} data bytes its header declares")
    array = np.frombuffer(buffer, dtype=dtype)
    return array.reshape(shape[::-1]).transpose() if fortran else array.reshape(shape)


def read_npy(data: bytes, field: str, max_cloud_points: int) -> np.ndarray:
    """An [N, 3] numeric array; object arrays are refused (loading them would need pickle)."""

    def cloud_shape(shape: tuple[int, ...]) -> None:
        if len(shape) != 2 or shape[1] != 3:
            raise InvalidInput(field, f"NPY array must be N x 3, got shape {list(shape)[:8]}")
        if shape[0] > max_cloud_points:
            raise _too_many(field, shape[0], max_cloud_points)

    return _npy_array(io.BytesIO(data), field, cloud_shape)


def read_pair(data: bytes, max_cloud_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Source and target from one raw body: NPY of shape [2, N, 3], or NPZ with arrays `source` and `target`."""
    kind = detect_format(data)
    if kind == "npy":

        def pair_shape(shape: tuple[int, ...]) -> None:
            if len(shape) != 3 or shape[0] != 2 or shape[2] != 3:
                raise InvalidInput(
                    "body", f"a raw NPY body must be a numeric [2, N, 3] array (source, target), got {list(shape)[:8]}"
                )
            if shape[1] > max_cloud_points:
                raise _too_many("body", shape[1], max_cloud_points)

        pair = _npy_array(io.BytesIO(data), "body", pair_shape)
        return as_points(pair[0], "source"), as_points(pair[1], "target")
    if kind == "npz":
        return _read_npz_pair(data, max_cloud_points)
    if kind in ("ply", "pcd"):
        raise UnsupportedFormat(
            f"body: a raw {kind.upper()} body holds one cloud; send source and target as multipart/form-data file parts"
        )
    raise UnsupportedFormat("body: unrecognised format; send NPY ([2, N, 3]) or NPZ (`source`, `target`) bytes")


def _archive_directory(data: bytes) -> tuple[int, int]:
    """(members, directory bytes) as the archive's end records declare them, read before zipfile parses
    the directory, whose every entry it would otherwise turn into an object."""
    end = data.rfind(b"PK\x05\x06", max(0, len(data) - 22 - 0xFFFF))
    if end < 0 or len(data) < end + 22:
        raise InvalidInput("body", "unreadable NPZ archive: it has no end-of-archive record (truncated?)")
    _, _, _, _, members, directory_bytes, _, _ = struct.unpack("<4s4H2LH", data[end : end + 22])
    locator = end - 20
    if locator >= 56 and data[locator : locator + 4] == b"PK\x06\x07":  # ZIP64: the real values are further back
        record = data[locator - 56 : locator]
        if record[:4] == b"PK\x06\x06":
            members, directory_bytes = struct.unpack("<QQ", record[32:48])
    return members, directory_bytes


def _member_names(names) -> str:
    shown = [name[:64] for name in sorted(names)[:SHOWN_NAMES]]
    more = len(names) - len(shown)
    return f"{shown}" + (f" and {more} more" if more > 0 else "")


def _read_npz_pair(data: bytes, max_cloud_points: int) -> tuple[np.ndarray, np.ndarray]:
    limit = max_cloud_points * 3 * 8 + 4096  # the largest acceptable float64 cloud plus its NPY header
    members, directory_bytes = _archive_directory(data)
    if members > MAX_ARCHIVE_MEMBERS or directory_bytes > MAX_ARCHIVE_DIRECTORY_BYTES:
        raise InvalidInput(
            "body",
            f"the NPZ archive lists {members} members in a {directory_bytes}-byte directory; send one with just "
            f"`source` and `target` (at most {MAX_ARCHIVE_MEMBERS} members)",
        )
    try:
        archive = zipfile.ZipFile(io.BytesIO(data))
        infos = {info.filename: info for info in archive.infolist()}
    except ARCHIVE_ERRORS as error:
        raise InvalidInput("body", f"unreadable NPZ archive: {str(error)[:200]}") from None
    if len(infos) > MAX_ARCHIVE_MEMBERS:
        raise InvalidInput("body", f"the NPZ archive holds {len(infos)} members, more than {MAX_ARCHIVE_MEMBERS}")
    clouds = []
    for name in ("source", "target"):
        info = infos.get(f"{name}.npy")
        if info is None:
            raise InvalidInput(name, f"the NPZ archive has no `{name}` array (it has {_member_names(infos)})")
        if info.flag_bits & 0x1:
            raise InvalidInput(name, "the NPZ array is encrypted; send an archive without a password")
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            raise InvalidInput(
                name,
                f"the NPZ array uses compression method {info.compress_type}; save it with numpy's savez or "
                "savez_compressed (stored or deflate)",
            )
        if info.file_size > limit:
            raise InvalidInput(
                name,
                f"the NPZ array is {info.file_size} bytes uncompressed, more than a cloud of {max_cloud_points} points",
            )

        def cloud_shape(shape: tuple[int, ...], name: str = name) -> None:
            if len(shape) != 2 or shape[1] != 3:
                raise InvalidInput(name, f"NPY array must be N x 3, got shape {list(shape)[:8]}")
            if shape[0] > max_cloud_points:
                raise _too_many(name, shape[0], max_cloud_points)

        try:
            # zipfile inflates at most what each read asks for and stops at the declared size, whose CRC it checks
            with archive.open(info) as stream:
                clouds.append(_npy_array(stream, name, cloud_shape))
        except InvalidInput:
            raise
        except ARCHIVE_ERRORS as error:
            raise InvalidInput(name, f"damaged NPZ archive member: {str(error)[:200]}") from None
    return as_points(clouds[0], "source"), as_points(clouds[1], "target")


# ---------------------------------------------------------------- writing (client side)


def write_ply(path: str | Path, points: np.ndarray) -> None:
    """A binary little-endian PLY with float32 x, y, z vertices."""
    from plyfile import PlyData, PlyElement

    vertices = np.empty(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    for index, axis in enumerate("xyz"):
        vertices[axis] = points[:, index]
    PlyData([PlyElement.describe(vertices, "vertex")]).write(str(path))
