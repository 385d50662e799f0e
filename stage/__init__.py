"""capture-stage: run a multi-camera capture stage and turn its takes into spines."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("capture-stage")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"

__all__ = ["__version__"]
