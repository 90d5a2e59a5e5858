"""What the training, evaluation and export command lines share: argument types that refuse
impossible numbers up front, readable weights files, and one-line errors for user mistakes."""

import argparse
import functools
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

T = TypeVar("T")

# Problems with paths the user gave (missing data, an output folder that is a file, no permission).
PATH_ERRORS = (FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError, PermissionError)


class UserError(Exception):
    """A problem with the command's input that the user can fix: printed as one line, exit status 2."""


def _number(kind: Callable[[str], T], lowest: T, inclusive: bool) -> Callable[[str], T]:
    bound = f"at least {lowest}" if inclusive else f"more than {lowest}"

    def parse(text: str) -> T:
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if value < lowest or (value == lowest and not inclusive):
            raise argparse.ArgumentTypeError(f"must be {bound}, got {text}")
        return value

    parse.__name__ = kind.__name__  # argparse names the type in its messages
    return parse


positive_int = _number(int, 0, inclusive=False)
non_negative_int = _number(int, 0, inclusive=True)
positive_float = _number(float, 0.0, inclusive=False)
non_negative_float = _number(float, 0.0, inclusive=True)


def load_torch_file(path: Path, what: str, *, weights_only: bool = True) -> dict:
    """A checkpoint or weights file on the CPU, or a UserError naming the file and the option."""
    import torch  # here, so that evaluating an ONNX file needs no torch

    if not path.is_file():
        raise UserError(f"{what} {path}: no such file")
    try:
        return torch.load(path, map_location="cpu", weights_only=weights_only)
    except Exception:  # torch raises several types, with long messages, for files it cannot read
        raise UserError(f"{what} {path}: not a torch checkpoint or weights file torch can read") from None


def reports_user_errors(prog: str) -> Callable[[Callable[..., T]], Callable[..., T]]:
    """Turn UserError and path errors escaping `main` into `prog: error: ...` and exit status 2."""

    def decorate(main: Callable[..., T]) -> Callable[..., T]:
        @functools.wraps(main)
        def run(*args, **kwargs) -> T:
            try:
                return main(*args, **kwargs)
            except (UserError, *PATH_ERRORS) as error:
                print(f"{prog}: error: {error}", file=sys.stderr)
                raise SystemExit(2) from None

        return run

    return decorate
