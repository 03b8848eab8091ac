"""Options of meshing a fused cloud (:mod:`dvpmvs.meshing`)."""

from __future__ import annotations

from dataclasses import dataclass

from dvpmvs.validation import check_field_types, check_threads

__all__ = ["MESHING_METHODS", "MeshingOptions"]


MESHING_METHODS = ("poisson", "colmap_poisson", "delaunay")


@dataclass(frozen=True)
class MeshingOptions:
    """Meshing a fused cloud.

    Parameters
    ----------
    method : str
        ``poisson`` (Open3D), ``colmap_poisson`` (pycolmap) or ``delaunay`` (COLMAP's program).
    depth : int
        The Poisson octree depth (2^depth cells across the cloud's bounding box).
    trim_quantile : float
        ``poisson`` removes the vertices of the lowest sample density, this share of them.
    colmap_trim : float
        ``colmap_poisson``'s trim (COLMAP's density value).
    colmap_binary : str
        The COLMAP program ``delaunay`` runs.
    num_threads : int
        1 keeps the mesh's bytes reproducible (see the module doc); 0 uses every core.
    """

    method: str = "poisson"
    depth: int = 11
    trim_quantile: float = 0.05
    colmap_trim: float = 7.0
    colmap_binary: str = "colmap"
    num_threads: int = 1

    def __post_init__(self):
        check_field_types(self, "meshing.")
        if self.method not in MESHING_METHODS:
            raise ValueError(
                f"meshing.method must be one of {', '.join(MESHING_METHODS)}, got {self.method!r}"
            )
        if not 5 <= self.depth <= 16:
            raise ValueError(f"meshing.depth must be in [5, 16], got {self.depth}")
        if not 0 <= self.trim_quantile < 1:
            raise ValueError(f"meshing.trim_quantile must be in [0, 1), got {self.trim_quantile}")
        if self.colmap_trim < 0:
            raise ValueError(f"meshing.colmap_trim must be >= 0, got {self.colmap_trim}")
        check_threads("meshing.num_threads", self.num_threads)
