"""dvpmvs: CPU multi-view stereo (DVP-MVS++) as a drop-in replacement for COLMAP's dense stage.

Data flows one way: :mod:`dvpmvs.workspace` -> priors -> estimator -> :mod:`dvpmvs.maps` ->
fusion -> evaluation. Pluggable parts are found through entry points (:mod:`dvpmvs.registry`).
"""

__version__ = "0.1.0"
