"""Queries of a COLMAP sparse model that the dense stage needs: which points each view
observes, the views' depth ranges (as COLMAP's ``ComputeDepthRanges``) and the views' shared
points with their triangulation angles (what view selectors rank on). COLMAP keeps these in
``mvs/model.h``, apart from the workspace's layout (:mod:`dvpmvs.workspace`)."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np
import pycolmap

from dvpmvs.errors import DvpmvsError

if TYPE_CHECKING:
    from dvpmvs.view import View

__all__ = ["SparseModel", "NoDepthRangeError", "DepthRange"]

log = logging.getLogger(__name__)


class NoDepthRangeError(DvpmvsError, ValueError):
    """No view observes enough sparse points for a depth range."""


@dataclass(frozen=True)
class DepthRange:
    """A view's depth range, the sparse points in front of it it was estimated from, and whether
    it is the scene's range for want of them (``fallback``)."""

    range: tuple[float, float]
    num_points: int = 0
    fallback: bool = False


class SparseModel:
    """The sparse points of ``reconstruction`` as the ``views`` (name -> view, in a fixed order)
    observe them."""

    def __init__(self, reconstruction: pycolmap.Reconstruction, views: Mapping[str, View]):
        self.reconstruction = reconstruction
        self.views = views

    @cached_property
    def observations(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The sparse observations as flat arrays: ``xyz`` (P, 3) of the points seen by a view,
        and per observation its point index and view index (into ``views``), grouped by
        point. A point observed twice in one image counts once there."""
        index = {view.image_id: k for k, view in enumerate(self.views.values())}
        xyz, obs_point, obs_view = [], [], []
        for point in self.reconstruction.points3D.values():
            seen = sorted({index[e.image_id] for e in point.track.elements if e.image_id in index})
            if seen:
                obs_point.extend([len(xyz)] * len(seen))
                obs_view.extend(seen)
                xyz.append(point.xyz)
        return (
            np.asarray(xyz, dtype=np.float64).reshape(-1, 3),
            np.asarray(obs_point, dtype=np.int64),
            np.asarray(obs_view, dtype=np.int64),
        )

    def depth_ranges(
        self,
        depth_quantiles: tuple[float, float],
        depth_margin: float,
        min_points_for_range: int,
        depth_range: tuple[float, float] | None = None,
        where: object = "the model",
    ) -> dict[str, DepthRange]:
        """Per view name its depth range (as COLMAP's ``Model::ComputeDepthRanges``): the
        nearest-rank ``depth_quantiles`` of the depths of the points it observes, stretched by
        ``depth_margin``; a view with fewer than ``min_points_for_range`` points gets the scene's
        range and a warning (``where``: the workspace, for the error when no view has enough).
        A given ``depth_range`` is every view's (no point is counted then)."""
        if depth_range is not None:
            fixed = (float(depth_range[0]), float(depth_range[1]))
            return {name: DepthRange(fixed) for name in self.views}
        counts = {}
        estimated: dict[str, tuple[float, float]] = {}
        lo_q, hi_q = depth_quantiles
        for view in self.views.values():
            points = self.observed_points(view.name)
            depths = np.sort((points @ view.R[2]) + view.t[2])
            depths = depths[depths > 0]
            counts[view.name] = int(depths.size)
            if depths.size >= min_points_for_range:
                # Nearest-rank quantiles on the sorted depths, as COLMAP's ComputeDepthRanges.
                lo = depths[min(int(depths.size * lo_q), depths.size - 1)]
                hi = depths[min(int(depths.size * hi_q), depths.size - 1)]
                estimated[view.name] = (
                    float(lo * (1 - depth_margin)),
                    float(hi * (1 + depth_margin)),
                )
        if not estimated:
            raise NoDepthRangeError(
                f"no image of {where} observes at least {min_points_for_range} sparse "
                f"points in front of it, so no depth range can be estimated; triangulate the model "
                f"(colmap point_triangulator) or give depth_range=[min,max]"
            )
        fallback = (min(r[0] for r in estimated.values()), max(r[1] for r in estimated.values()))
        ranges = {}
        for name in self.views:
            if name in estimated:
                ranges[name] = DepthRange(estimated[name], counts[name])
                continue
            ranges[name] = DepthRange(fallback, counts[name], fallback=True)
            log.warning(
                "image %s observes %d sparse point(s) (< %d); using the scene's depth range "
                "[%.4g, %.4g] instead",
                name,
                counts[name],
                min_points_for_range,
                *fallback,
            )
        return ranges

    @cached_property
    def point_ids_by_view(self) -> list[np.ndarray]:
        """Per view (in the order of ``views``) the ascending indices (into ``observations``'
        points) of the points it observes."""
        _, obs_point, obs_view = self.observations
        by_view = np.argsort(obs_view, kind="stable")
        bounds = np.searchsorted(obs_view[by_view], np.arange(len(self.views) + 1))
        return [obs_point[by_view[bounds[k] : bounds[k + 1]]] for k in range(len(self.views))]

    @cached_property
    def _index(self) -> dict[str, int]:
        """Image name -> its position in ``views``."""
        return {name: k for k, name in enumerate(self.views)}

    def observed_points(self, name: str) -> np.ndarray:
        """(N, 3) world coordinates of the sparse points image ``name`` observes (gathered on
        each call: holding them per view would double the model's memory)."""
        return self.observations[0][self.point_ids_by_view[self._index[name]]]

    @cached_property
    def covisibility(self) -> Mapping[str, dict[str, np.ndarray]]:
        """name -> other name -> triangulation angles (degrees) of the sparse points both observe;
        the length of each array is the number of shared points. View selectors rank on this.

        Computed for one reference when it is looked up (:meth:`shared_points`) and not kept:
        the pairs of every view with every other are as many as the sum over points of the
        square of their track lengths, which for a large survey does not fit in memory."""
        return _Covisibility(self)

    def shared_points(self, name: str) -> dict[str, np.ndarray]:
        """other name -> triangulation angles (degrees) of the points ``name`` and the other view
        both observe, for every view that shares one with ``name`` (in the order of ``views``).
        Each array is ordered by track length, then by whether ``name`` comes first in the
        track, then by point."""
        names = list(self.views)
        reference = self._index[name]
        xyz, obs_point, obs_view = self.observations
        track_length, track_start = self._tracks
        mine = np.flatnonzero(obs_view == reference)
        points = obs_point[mine]
        length = track_length[points]
        # Every observation of every point the reference observes, with its position in the track.
        total = int(length.sum())
        point = np.repeat(points, length)
        position = np.arange(total) - np.repeat(np.cumsum(length) - length, length)
        view = obs_view[track_start[point] + position]
        reference_first = np.repeat(mine - track_start[points], length) < position
        other = view != reference
        point, view, reference_first = point[other], view[other], reference_first[other]
        centres = self._centres
        X = xyz[point]
        ray_a, ray_b = centres[reference] - X, centres[view] - X
        norms = np.linalg.norm(ray_a, axis=1) * np.linalg.norm(ray_b, axis=1)
        cosine = np.divide(
            (ray_a * ray_b).sum(axis=1), norms, out=np.ones_like(norms), where=norms > 0
        )
        angle = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))
        order = np.lexsort((point, ~reference_first, track_length[point], view))
        view, angle = view[order], angle[order]
        cuts = np.flatnonzero(np.diff(view)) + 1
        return {
            names[int(v[0])]: a
            for v, a in zip(np.split(view, cuts), np.split(angle, cuts))
            if v.size
        }

    @cached_property
    def _tracks(self) -> tuple[np.ndarray, np.ndarray]:
        """Per point: its track length (views observing it) and its first observation's index."""
        xyz, obs_point, _ = self.observations
        length = np.bincount(obs_point, minlength=len(xyz))
        return length, np.concatenate([[0], np.cumsum(length)[:-1]]).astype(np.int64)

    @cached_property
    def _centres(self) -> np.ndarray:
        return np.array([view.center for view in self.views.values()]).reshape(-1, 3)

    def overlaps(self, view: View) -> bool:
        """Whether ``view`` shares a sparse point with one of its sources. A model without points
        (depth ranges given by hand) gives no evidence either way: every view overlaps."""
        if not len(self.observations[0]):
            return True
        mine = self.point_ids_by_view[self._index[view.name]]
        return any(
            np.intersect1d(mine, self.point_ids_by_view[self._index[name]], assume_unique=True).size
            for name in view.sources
        )


class _Covisibility(Mapping):
    """A read-only mapping name -> :meth:`SparseModel.shared_points`, computed on each lookup."""

    def __init__(self, model: SparseModel):
        self._model = model

    def __getitem__(self, name: str) -> dict[str, np.ndarray]:
        if name not in self._model.views:
            raise KeyError(name)
        return self._model.shared_points(name)

    def __iter__(self):
        return iter(self._model.views)

    def __len__(self) -> int:
        return len(self._model.views)
