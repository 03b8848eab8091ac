"""The installed dvpmvs's version (a leaf: what records and the command line print)."""

from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("dvpmvs")
except PackageNotFoundError:  # run from a source tree that was never installed
    __version__ = "0+unknown"
