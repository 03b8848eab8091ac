"""dvpmvs: CPU multi-view stereo (DVP-MVS++) as a drop-in replacement for COLMAP's dense stage.

Data flows one way: :mod:`dvpmvs.workspace` -> priors -> estimator -> :mod:`dvpmvs.maps` ->
fusion -> evaluation. Pluggable parts are found through entry points (:mod:`dvpmvs.registry`).

The Python API (:mod:`dvpmvs.api`, pycolmap's names): :func:`patch_match_stereo`,
:func:`stereo_fusion`, :func:`poisson_meshing`, :func:`delaunay_meshing`, :func:`reconstruct`,
:func:`dense_options`; importing ``dvpmvs`` loads none of them until one is used.
"""

from dvpmvs._version import __version__

_API = (
    "delaunay_meshing",
    "dense_options",
    "patch_match_stereo",
    "poisson_meshing",
    "reconstruct",
    "stereo_fusion",
)

__all__ = ["__version__", *_API]


def __getattr__(name: str):
    if name in _API:
        from dvpmvs import api

        return getattr(api, name)
    raise AttributeError(f"module 'dvpmvs' has no attribute {name!r}")
