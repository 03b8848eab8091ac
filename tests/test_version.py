"""The version the records and ``dvpmvs --version`` print is the installed distribution's."""

from importlib.metadata import version

from dvpmvs import __version__
from dvpmvs._version import __version__ as recorded


def test_the_version_is_the_installed_distributions():
    assert __version__ == recorded == version("dvpmvs")
