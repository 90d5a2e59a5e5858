"""ifnet-serve: IFNet point-cloud registration over HTTP, run with ONNX Runtime (no torch)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("ifnet-serve")
except PackageNotFoundError:  # running from a source checkout
    __version__ = "0+unknown"
