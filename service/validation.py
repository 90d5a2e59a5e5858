"""Checks of what users send: clouds as N x 3 finite numbers, rigid 4x4 matrices, cloud sizes and
degeneracy. Every failure is an InvalidInput naming the field and the problem."""

from collections.abc import Sequence
from typing import Any

import numpy as np
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from model.geometry import degeneracy, from_matrix, nearest_rotation, remove_duplicates, rigidity_error, to_matrix

INIT_RIGIDITY_TOLERANCE = 1e-3  # accepts matrices printed with a few decimals
MAX_COORDINATE = 1e12  # beyond this, squared distances lose all precision (and eventually overflow)


class InvalidInput(ValueError):
    """Input that cannot be registered; `field` names the offending part of the request."""

    def __init__(self, field: str, problem: str):
        super().__init__(f"{field}: {problem}")
        self.field = field
        self.problem = problem


def invalid_request(error: ValidationError, *location: str) -> RequestValidationError:
    """A request's values that fail their schema, answered 422 naming the field (under `location`).
    A ValidationError left as it is comes from the service's own answer: a 500, logged."""
    errors = error.errors(include_url=False, include_input=False)
    return RequestValidationError([{**item, "loc": (*location, *item["loc"])} for item in errors])


def as_points(value: Any, field: str) -> np.ndarray:
    """An N x 3 float64 array of finite coordinates from nested lists or an array, or InvalidInput."""
    if isinstance(value, np.ndarray):
        array = value
        if array.dtype.kind not in "fiu":
            raise InvalidInput(field, f"coordinates must be numbers, got an array of {array.dtype}")
    else:
        try:
            array = np.asarray(value)
        except ValueError:  # ragged nesting
            raise InvalidInput(field, _describe_rows(value)) from None
        if array.dtype.kind not in "fiu":
            raise InvalidInput(field, _describe_rows(value))
    if array.size == 0:
        raise InvalidInput(field, "is empty; send a list of [x, y, z] points")
    if array.ndim != 2 or array.shape[1] != 3:
        if array.ndim < 2 and not isinstance(value, np.ndarray):
            raise InvalidInput(field, _describe_rows(value))
        raise InvalidInput(field, f"must be a list of [x, y, z] points (N x 3), got shape {list(array.shape)}")
    if not isinstance(value, np.ndarray) and _has_bool(value):
        raise InvalidInput(field, _describe_rows(value))
    array = array.astype(np.float64, copy=False)
    finite = np.isfinite(array).all(axis=1)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise InvalidInput(
            field,
            f"{len(bad)} point(s) have NaN or infinite coordinates (first at index {bad[0]}: "
            f"{array[bad[0]].tolist()}); drop or repair them before sending",
        )
    if np.abs(array).max() > MAX_COORDINATE:
        raise InvalidInput(field, f"has coordinates beyond ±{MAX_COORDINATE:g}; shift or rescale the cloud first")
    return array


def _has_bool(value: Any) -> bool:
    """Whether N x 3 nested rows hold a true/false, which numpy would quietly read as 1/0."""
    return any(type(coordinate) is bool for row in value for coordinate in row)


def _describe_rows(value: Any) -> str:
    """Why nested lists are not N x 3 numbers, pointing at the first bad row."""
    if not isinstance(value, Sequence) or isinstance(value, str | bytes):
        return f"must be a list of [x, y, z] points, got {type(value).__name__}"
    for index, row in enumerate(value):
        if not isinstance(row, Sequence) or isinstance(row, str | bytes):
            return f"point {index} must be a list [x, y, z], got {type(row).__name__}"
        if len(row) != 3:
            return f"point {index} has {len(row)} coordinates; every point needs exactly 3 (x, y, z)"
        for coordinate in row:
            if isinstance(coordinate, bool) or not isinstance(coordinate, int | float):
                return f"point {index} has a non-numeric coordinate {coordinate!r}"
            if abs(coordinate) > MAX_COORDINATE:
                return f"point {index} has a coordinate beyond ±{MAX_COORDINATE:g}; shift or rescale the cloud first"
    return "must be a list of [x, y, z] points (N x 3)"


def _only_numbers(value: Any) -> bool:
    if isinstance(value, list | tuple):
        return all(_only_numbers(item) for item in value)
    return isinstance(value, int | float) and not isinstance(value, bool)


def as_rigid_transform(value: Any, field: str = "init") -> np.ndarray:
    """A proper rigid 4x4 matrix (rotation re-orthonormalised), or InvalidInput."""
    if not isinstance(value, np.ndarray) and not _only_numbers(value):  # numpy would read "1" and true as numbers
        raise InvalidInput(field, "must be a 4x4 matrix of numbers (not strings or true/false)")
    try:
        matrix = np.asarray(value, dtype=np.float64)
    except (ValueError, TypeError):
        raise InvalidInput(field, "must be a 4x4 matrix of numbers (a list of 4 rows of 4)") from None
    if matrix.shape != (4, 4):
        raise InvalidInput(field, f"must be a 4x4 matrix, got shape {list(matrix.shape)}")
    if not np.isfinite(matrix).all():
        raise InvalidInput(field, "contains NaN or infinite values")
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: not rigid, and no warning about it
        error = rigidity_error(matrix)
    if not error <= INIT_RIGIDITY_TOLERANCE:
        raise InvalidInput(
            field,
            "is not a rigid transform: its upper-left 3x3 must be a rotation (orthonormal, determinant +1) "
            f"and its last row [0, 0, 0, 1] (deviation {error:.3g}, tolerance {INIT_RIGIDITY_TOLERANCE:g})",
        )
    rotation, translation = from_matrix(matrix)
    if np.abs(translation).max() > MAX_COORDINATE:
        raise InvalidInput(field, f"has a translation beyond ±{MAX_COORDINATE:g}, like the clouds' coordinates")
    return to_matrix(nearest_rotation(rotation), translation)


def check_cloud(points: np.ndarray, field: str, min_points: int, max_cloud_points: int) -> np.ndarray:
    """Size and degeneracy checks; returns the cloud without exact duplicates (first ones kept)."""
    if len(points) > max_cloud_points:
        raise InvalidInput(
            field, f"has {len(points)} points, more than the limit of {max_cloud_points}; subsample it first"
        )
    if len(points) < min_points:
        raise InvalidInput(field, f"has {len(points)} points; at least {min_points} distinct points are needed")
    if (reason := degeneracy(points)) is not None:
        if reason == "collinear":
            problem = "all points lie on one line (or a few lie so far from the rest that they look so: remove them)"
        elif np.ptp(points, axis=0).max() > 0:  # distinct, but not at the precision of coordinates this large
            largest = float(np.abs(points).max())
            problem = (
                f"all points coincide to within the rounding of coordinates up to {largest:.3g} "
                "(shift it nearer the origin)"
            )
        else:
            problem = "all points are identical"
        raise InvalidInput(field, f"is degenerate: {problem}, so no rigid transform can be determined")
    unique = remove_duplicates(points)
    if len(unique) < min_points:
        raise InvalidInput(
            field,
            f"has only {len(unique)} distinct points ({len(points) - len(unique)} exact duplicates); "
            f"at least {min_points} are needed",
        )
    return unique
