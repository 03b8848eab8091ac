"""The depth-normal-edge aligned prior (paper section 3.3): homogeneous regions for patch deformation.

1. Edges split the image into dispersed regions (4-connected components of non-edge pixels).
2. Every region above ``min_region`` pixels (eta) gets a RANSAC plane on the depth prior
   back-projected with K, and the plane's inlier ratio r.
3. Erosion (eq. 6): a region is pre-divided into the connected inliers of its plane and the
   rest, then divided again: along the turn of the normals with an independent normal prior
   (two groups of normals), else each pixel to the nearer of the two planes; the division
   stands when the two planes differ (Psi <= varphi), fit better
   ((r_i + r_j) / 2 r_k >= gamma) and the normals along their boundary fluctuate (mean Phi <= phi).
   Where an independent normal prior shows no turn, the division is a depth step, and its planes
   must also be nearly parallel (within ``max_step_tilt``; our addition).
4. Dilation (eq. 7): neighbouring regions merge when their planes agree (Psi >= varphi), both fit
   well (r >= kappa) and the normals along their boundary are smooth (mean Phi >= phi).
5. Pixel filtering (eq. 8): a homogeneous-boundary pixel (in no region: an edge pixel) joins a
   neighbouring planar region when it lies on its plane (distance <= delta) with a smooth normal
   (Phi >= phi) and, with an independent normal prior, a normal within phi of the plane's
   (|n_p . n_k| >= phi). Pixels of regions too small for a plane keep their region.

Output: an int32 label map, 0 on homogeneous boundaries (pixels in no region).

Units (the paper leaves them open; our decisions): distances to and between planes are relative
to the pixel's depth and measured in one ``distance_unit`` (2 % of depth): RANSAC inliers lie
within one unit, pixel filtering accepts up to delta = 0.8 units, and Psi = n_i . n_j - min(1,
gap / distance_unit), with gap the median relative depth difference of the two planes along the
pixels they share a boundary with, or, where larger, that of the two planes moved onto the depth
prior of their pixels within ``seam_band`` pixels of the boundary (the step at the seam; our
addition). Eq. 4's |d_i - d_j| and eq. 8's |n_k . p + d_k| are both plane offsets in the same
space, so they share the unit: parallel planes merge (Psi >= varphi = 0.5) when they lie less
than half a unit (1 % of depth) apart.

The depth-edge rule: a pixel is heterogeneous where the depth prior, normalised to [0, 1] over
the view's depth range, changes by more than epsilon = 0.005 per pixel in the 4 directions (its
Phi is 0 there, 1 elsewhere). Without a normal prior (``w/o Mon``: DVP-MVS's depth-edge prior)
that is Phi; with an independent one, Phi is the smaller of it and eq. 5, so that a boundary
fluctuates where either the depth steps or the normal turns; with normals computed from the
depth prior itself, Phi is eq. 5.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from dvpmvs.geometry import RansacPlanes, back_project
from dvpmvs.options.segmentation import PAPER_SYMBOLS, SegmentationOptions

__all__ = [
    "SegmentationOptions",
    "PAPER_SYMBOLS",
    "Segmentation",
    "normal_similarity",
    "segment",
]


# The paper's symbols for the aligned prior's parameters of its Table V, and the options they are.


@dataclass
class Segmentation:
    """labels (H, W) int32, 0 on boundaries; planes (R + 1, 4) [n, d] per label (NaN: none);
    inlier_ratio (R + 1,); counts of the splits and merges made."""

    labels: np.ndarray
    planes: np.ndarray
    inlier_ratio: np.ndarray
    splits: int = 0
    merges: int = 0
    filtered: int = 0


def _shift(array: np.ndarray, dy: int, dx: int, fill) -> np.ndarray:
    """out[r, c] = array[r + dy, c + dx], ``fill`` outside."""
    out = np.full_like(array, fill)
    h, w = array.shape[:2]
    ys, yd = (slice(dy, h), slice(0, h - dy)) if dy >= 0 else (slice(0, h + dy), slice(-dy, h))
    xs, xd = (slice(dx, w), slice(0, w - dx)) if dx >= 0 else (slice(0, w + dx), slice(-dx, w))
    out[yd, xd] = array[ys, xs]
    return out


def normal_similarity(normal: np.ndarray, search: int) -> np.ndarray:
    """Phi (eq. 5): per pixel the minimum dot product between its normal and the normals up to
    ``search`` pixels away in the 4 directions (the widened 4-neighbourhood)."""
    phi = np.ones(normal.shape[:2], np.float32)
    for step in range(1, search + 1):
        for dy, dx in ((-step, 0), (step, 0), (0, -step), (0, step)):
            other = _shift(normal, dy, dx, 0.0)
            dot = (normal * other).sum(axis=2)
            inside = np.any(other != 0, axis=2)
            phi = np.where(inside, np.minimum(phi, dot), phi)
    return phi


def _depth_smoothness(
    depth: np.ndarray, depth_range: tuple[float, float], epsilon: float, search: int
) -> np.ndarray:
    """Phi without normals: 1 where the normalised depth changes by <= epsilon per pixel."""
    lo, hi = depth_range
    norm = (depth - lo) / (hi - lo)
    smooth = np.ones(depth.shape, bool)
    for step in range(1, search + 1):
        for dy, dx in ((-step, 0), (step, 0), (0, -step), (0, step)):
            other = _shift(norm, dy, dx, np.nan)
            smooth &= ~(np.abs(other - norm) > epsilon * step)
    return smooth.astype(np.float32)


def _plane_depth(plane: np.ndarray, rays: np.ndarray) -> np.ndarray:
    denom = rays @ plane[:3]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(np.abs(denom) > 1e-12, -plane[3] / denom, np.nan)


def _plane_gap(plane_i: np.ndarray, plane_j: np.ndarray, rays: np.ndarray) -> float:
    """Median relative depth difference of two planes along ``rays`` (1 where undefined)."""
    zi, zj = _plane_depth(plane_i, rays), _plane_depth(plane_j, rays)
    gap = np.abs(zi - zj) / np.maximum(np.minimum(np.abs(zi), np.abs(zj)), 1e-12)
    return float(np.nanmedian(gap)) if np.isfinite(gap).any() else 1.0


def _seam_planes(
    mask_i: np.ndarray,
    mask_j: np.ndarray,
    plane_i: np.ndarray,
    plane_j: np.ndarray,
    planes: RansacPlanes,
    band: int,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Each side's plane moved (normal kept, offset the median of its pixels') onto the depth
    prior of its pixels within ``band`` of the other side; None when a side has no such pixel.
    A region's plane is fitted to all of it, and the prior's smooth scale errors tilt and shift
    it, so two planes can meet at a boundary where the surface steps (a window pane a few cm
    behind its wall) or part there where it does not; the prior next to the seam shows the step."""
    near = _boundary_pixels(mask_i, mask_j, band)
    near = near[planes.valid[near]]
    moved = []
    for mask, plane in ((mask_i, plane_i), (mask_j, plane_j)):
        side = near[mask.ravel()[near]]
        if side.size == 0:
            return None
        moved.append(np.append(plane[:3], np.median(-(planes.points[side] @ plane[:3]))))
    return moved[0], moved[1]


def _psi(
    plane_i: np.ndarray,
    plane_j: np.ndarray,
    rays: np.ndarray,
    options: SegmentationOptions,
    seam: tuple[np.ndarray, np.ndarray] | None = None,
) -> float:
    """Plane similarity (eq. 4): normal agreement minus the depth gap along the shared boundary
    (``rays``): the gap between the two planes, or with ``seam`` (``_seam_planes``) the larger of
    that and the gap between the planes moved onto the prior next to the boundary."""
    gap = _plane_gap(plane_i, plane_j, rays)
    if seam is not None:
        gap = max(gap, _plane_gap(seam[0], seam[1], rays))
    return float(plane_i[:3] @ plane_j[:3]) - min(1.0, gap / options.distance_unit)


def _boundary_pixels(mask_i: np.ndarray, mask_j: np.ndarray, radius: int) -> np.ndarray:
    """Flat indices of the pixels of either mask within ``radius`` of the other. The masks are
    dilated within their bounding box widened by ``radius`` only: that holds every pixel the
    dilation can reach, and a region is often a small part of the image."""
    rows, cols = np.nonzero(mask_i | mask_j)
    if rows.size == 0:
        return np.zeros(0, np.intp)
    h, w = mask_i.shape
    r0, r1 = max(rows.min() - radius, 0), min(rows.max() + radius + 1, h)
    c0, c1 = max(cols.min() - radius, 0), min(cols.max() + radius + 1, w)
    crop_i, crop_j = mask_i[r0:r1, c0:c1], mask_j[r0:r1, c0:c1]
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    near_j = cv2.dilate(crop_j.astype(np.uint8), kernel) > 0
    near_i = cv2.dilate(crop_i.astype(np.uint8), kernel) > 0
    row, col = np.nonzero((crop_i & near_j) | (crop_j & near_i))
    return (row + r0) * w + (col + c0)


def _two_normal_groups(
    normals: np.ndarray,
    centre_i: np.ndarray,
    centre_j: np.ndarray,
    max_similarity: float,
    iterations: int = 5,
) -> np.ndarray | None:
    """Mask of the unit ``normals`` (N, 3) nearer to centre i than to centre j, after a few
    rounds of 2-means on the sphere from the given centres; None when the two groups' mean
    normals agree beyond ``max_similarity`` (no turn for Phi to see, e.g. a depth step)."""
    for _ in range(iterations + 1):
        group_i = normals @ centre_i >= normals @ centre_j
        if group_i.all() or not group_i.any():
            return None
        centre_i = normals[group_i].sum(axis=0)
        centre_j = normals[~group_i].sum(axis=0)
        centre_i = centre_i / max(float(np.linalg.norm(centre_i)), 1e-12)
        centre_j = centre_j / max(float(np.linalg.norm(centre_j)), 1e-12)
    if float(centre_i @ centre_j) > max_similarity:
        return None
    return normals @ centre_i >= normals @ centre_j


def _main_piece(mask: np.ndarray, region_mask: np.ndarray) -> np.ndarray:
    """The largest 4-connected piece of ``mask`` after a 5 x 5 closing and opening (thin lines
    and specks of either group go to the other), within ``region_mask``."""
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    clean = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE, kernel)
    clean = cv2.morphologyEx(clean, cv2.MORPH_OPEN, kernel) & region_mask.astype(np.uint8)
    count, pieces, stats, _ = cv2.connectedComponentsWithStats(clean, connectivity=4)
    if count < 2:
        return np.zeros_like(region_mask)
    return pieces == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))


def _fit_pair(planes: RansacPlanes, mask_i: np.ndarray, mask_j: np.ndarray, min_region: int):
    """(plane_i, r_i, plane_j, r_j) of two pixel masks, or None if one is small or has no plane."""
    if mask_i.sum() < min_region or mask_j.sum() < min_region:
        return None
    plane_i, r_i, _ = planes.fit(np.flatnonzero(mask_i.ravel()))
    plane_j, r_j, _ = planes.fit(np.flatnonzero(mask_j.ravel()))
    if not (np.isfinite(plane_i).all() and np.isfinite(plane_j).all()):
        return None
    return plane_i, r_i, plane_j, r_j


@dataclass
class _PriorGeometry:
    """What the stages read from one view's priors: the valid pixels, their camera-frame
    points and rays (flat), Phi per pixel (flat), the independent normals (flat; None when there
    are none or they were computed from the depth prior) and the plane fitter."""

    shape: tuple[int, int]
    valid: np.ndarray
    points: np.ndarray
    rays: np.ndarray
    phi: np.ndarray
    normals: np.ndarray | None
    planes: RansacPlanes


@dataclass
class _Regions:
    """The regions as the stages leave them: labels (0: boundary), each large region's plane
    and inlier ratio, and the next free label."""

    labels: np.ndarray
    planes: dict[int, np.ndarray]
    ratios: dict[int, float]
    next_label: int


def _members(labels: np.ndarray, label: int) -> np.ndarray:
    return np.flatnonzero(labels.ravel() == label)


def _region_index(labels: np.ndarray) -> dict[int, np.ndarray]:
    """The pixel lists of every region in one pass (sorted by label)."""
    flat = labels.ravel()
    order = np.argsort(flat, kind="stable")
    bounds = np.searchsorted(flat[order], np.arange(flat.max() + 2))
    return {
        k: order[bounds[k] : bounds[k + 1]]
        for k in range(1, flat.max() + 1)
        if bounds[k + 1] > bounds[k]
    }


def _prior_geometry(
    depth: np.ndarray,
    normal: np.ndarray | None,
    K: np.ndarray,
    depth_range: tuple[float, float],
    o: SegmentationOptions,
    depth_valid: np.ndarray | None,
    normal_from_depth: bool,
) -> _PriorGeometry:
    """Points, rays and Phi (eq. 5, with the depth-edge rule) of one view's priors."""
    valid = (depth > 0) & np.isfinite(depth) if depth_valid is None else depth_valid & (depth > 0)
    points = back_project(np.where(valid, depth, 1.0).astype(np.float64), K)
    rays = (points / points[..., 2:3]).reshape(-1, 3)
    planes = RansacPlanes(
        points, valid, o.distance_unit, o.ransac_iterations, o.ransac_points, o.seed
    )
    use_normals = o.use_normals and normal is not None
    phi = (
        normal_similarity(np.asarray(normal, np.float32), o.normal_search) if use_normals else None
    )
    # Independent normals add to the depth-edge rule, they do not replace it (section 3.3 defines
    # the heterogeneous region by the depth gradient, then brings in the normals): a step between
    # parallel planes (a window recess, a picture on a wall) keeps its normal on both sides.
    # Normals derived from the depth turn at its steps already, and the per-pixel threshold
    # would only add false steps on steep smooth surfaces.
    if not (use_normals and normal_from_depth):
        smooth = _depth_smoothness(
            np.where(valid, depth, np.nan), depth_range, o.depth_gradient, o.normal_search
        )
        phi = smooth if phi is None else np.minimum(phi, smooth)
    # Only independent normals can disagree with the depth prior: normals derived from that
    # depth turn where its planes meet, so they are no second opinion for erosion's division
    # or for filtering's check.
    independent = use_normals and not normal_from_depth
    normals = np.asarray(normal, np.float32).reshape(-1, 3) if independent else None
    return _PriorGeometry(depth.shape, valid, points, rays, phi.ravel(), normals, planes)


def _dispersed_regions(edges: np.ndarray, g: _PriorGeometry, o: SegmentationOptions) -> _Regions:
    """The edges' dispersed regions (4-connected components of non-edge pixels) and the RANSAC
    plane of each one of at least ``min_region`` (eta) pixels."""
    _, labels = cv2.connectedComponents((~edges).astype(np.uint8), connectivity=4)
    labels = labels.astype(np.int32)
    region_planes: dict[int, np.ndarray] = {}
    ratios: dict[int, float] = {}
    for label, pix in _region_index(labels).items():
        if pix.size >= o.min_region:
            region_planes[label], ratios[label], _ = g.planes.fit(pix)
    return _Regions(labels, region_planes, ratios, int(labels.max()) + 1)


def _erosion_eq6(regions: _Regions, g: _PriorGeometry, o: SegmentationOptions) -> int:
    """Erosion (eq. 6): split regions whose plane explains only part of them; returns the number
    of splits. A division stands when Psi <= varphi, (r_i + r_j) / 2 r_k >= gamma and the mean
    Phi along the new boundary <= phi."""
    h, w = g.shape
    planes, labels = g.planes, regions.labels
    split_by_normals = g.normals is not None and o.split_by_normals
    min_step_cos = np.cos(np.radians(o.max_step_tilt))
    splits = 0
    queue = [(label, 0) for label in sorted(regions.planes)]
    while queue:
        label, depth_round = queue.pop(0)
        pix = _members(labels, label)
        plane, r_k, inl = planes.fit(pix)
        if not np.isfinite(plane).all() or r_k >= 0.99:
            continue
        pix_valid = pix[g.valid.ravel()[pix]]
        mask_in = np.zeros(h * w, np.uint8)
        mask_in[pix_valid[inl]] = 1
        mask_in = cv2.morphologyEx(mask_in.reshape(h, w), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
        n_cc, cc, stats, _ = cv2.connectedComponentsWithStats(mask_in, connectivity=4)
        if n_cc < 2:
            continue
        biggest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        region_mask = labels == label
        mask_i = (cc == biggest) & region_mask
        mask_j = region_mask & ~mask_i
        fits = _fit_pair(planes, mask_i, mask_j, o.min_region)
        if fits is None:
            continue
        # One reassignment to the nearer plane moves the division from the edge of the
        # inlier band (a threshold away) onto the crease itself.
        # ... or, with an independent normal prior, onto the turn of its normals when they
        # turn far enough for eq. 6's Phi test: the region's normals in two groups (2-means
        # from the two planes' normals; the first group's main piece, cleaned of noise,
        # against the rest). The planes' intersection lies where the depth prior's scale
        # errors put it, on the suite's room often tens of pixels off the crease, where Phi
        # sees no turn.
        by_normals = (
            _two_normal_groups(g.normals[pix], fits[0][:3], fits[2][:3], o.normal_similarity)
            if split_by_normals
            else None
        )
        closer_i = (
            by_normals
            if by_normals is not None
            else planes.distance(fits[0], pix) <= planes.distance(fits[2], pix)
        )
        mask_i = np.zeros(h * w, bool)
        mask_i[pix[closer_i]] = True
        mask_i = mask_i.reshape(h, w)
        if by_normals is not None:
            mask_i = _main_piece(mask_i, region_mask)
        mask_j = region_mask & ~mask_i
        fits = _fit_pair(planes, mask_i, mask_j, o.min_region)
        if fits is None:
            continue
        plane_i, r_i, plane_j, r_j = fits
        # The normal prior shows no turn here, so the division can only be a depth step,
        # whose sides are parallel. Planes far apart in orientation are then the depth
        # prior's warp: a monocular prior's smooth scale error folds a flat wall into two
        # planes tens of degrees apart, which the normals contradict.
        if split_by_normals and by_normals is None and plane_i[:3] @ plane_j[:3] < min_step_cos:
            continue
        boundary = _boundary_pixels(mask_i, mask_j, 1)
        if boundary.size == 0:
            continue
        seam = (
            _seam_planes(mask_i, mask_j, plane_i, plane_j, planes, o.seam_band)
            if o.seam_band
            else None
        )
        psi = _psi(plane_i, plane_j, g.rays[boundary], o, seam)
        if (
            psi <= o.plane_similarity
            and (r_i + r_j) / (2 * max(r_k, 1e-6)) >= o.erosion_gain
            and g.phi[boundary].mean() <= o.normal_similarity
        ):
            splits += 1
            regions.planes[label], regions.ratios[label] = plane_i, r_i
            # The rest may fall apart: each connected piece becomes a region.
            n_rest, rest = cv2.connectedComponents(mask_j.astype(np.uint8), connectivity=4)
            for piece in range(1, n_rest):
                piece_mask = rest == piece
                new = regions.next_label
                labels[piece_mask] = new
                if piece_mask.sum() >= o.min_region:
                    regions.planes[new], regions.ratios[new], _ = planes.fit(
                        np.flatnonzero(piece_mask.ravel())
                    )
                    if depth_round + 1 < o.max_erosion_rounds:
                        queue.append((new, depth_round + 1))
                regions.next_label += 1
            regions.planes[label], regions.ratios[label], _ = planes.fit(_members(labels, label))
            if depth_round + 1 < o.max_erosion_rounds:
                queue.append((label, depth_round + 1))
    return splits


def _neighbouring_pairs(regions: _Regions, radius: int) -> dict[tuple[int, int], list[np.ndarray]]:
    """Pairs of large regions (u < v) closer than ``radius`` across an edge, with the pixels
    along their boundary."""
    labels, size = regions.labels, regions.next_label + 1
    big = np.zeros(size, bool)
    big[list(regions.planes)] = True
    pairs: dict[tuple[int, int], list[np.ndarray]] = {}
    flat = labels.ravel()
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            if (dy, dx) <= (0, 0) or dy * dy + dx * dx > radius * radius:
                continue
            other = _shift(labels, dy, dx, 0).ravel()
            m = (flat > 0) & (other > 0) & (flat != other) & big[flat] & big[other]
            if not m.any():
                continue
            pix = np.flatnonzero(m)
            a, b = flat[pix], other[pix]
            lo_l, hi_l = np.minimum(a, b), np.maximum(a, b)
            key = lo_l.astype(np.int64) * size + hi_l
            for k in np.unique(key):
                pairs.setdefault((int(k // size), int(k % size)), []).append(pix[key == k])
    return pairs


def _dilation_eq7(regions: _Regions, g: _PriorGeometry, o: SegmentationOptions) -> int:
    """Dilation (eq. 7): merge neighbouring regions on one plane; returns the number of merges.
    A pair merges when Psi >= varphi, both r >= kappa and the mean Phi along their boundary
    >= phi."""
    if len(regions.planes) <= 1:
        return 0
    pairs = _neighbouring_pairs(regions, o.adjacency_radius)
    parent = {label: label for label in regions.planes}

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    merges = 0
    planes, ratios = regions.planes, regions.ratios
    for u, v in sorted(pairs):
        boundary = np.unique(np.concatenate(pairs[(u, v)]))
        if ratios[u] < o.min_inlier_ratio or ratios[v] < o.min_inlier_ratio:
            continue
        psi = _psi(planes[u], planes[v], g.rays[boundary], o)
        if psi < o.plane_similarity or g.phi[boundary].mean() < o.normal_similarity:
            continue
        if o.seam_band:
            # The seam's gap can only lower Psi: measured for the pairs that pass the rest.
            # On the suite's facade (simulated priors) the regions' planes alone also merged
            # pairs of regions on two true planes (window panes a little behind the plaster);
            # the seam turns most of those away and almost none of the pairs on one plane.
            seam = _seam_planes(
                regions.labels == u,
                regions.labels == v,
                planes[u],
                planes[v],
                g.planes,
                o.seam_band,
            )
            if _psi(planes[u], planes[v], g.rays[boundary], o, seam) < o.plane_similarity:
                continue
        ru, rv = find(u), find(v)
        if ru != rv:
            parent[max(ru, rv)] = min(ru, rv)
            merges += 1
    if merges:
        lut = np.arange(regions.next_label + 1, dtype=np.int32)
        for label in parent:
            lut[label] = find(label)
        regions.labels = lut[regions.labels]
        index = _region_index(regions.labels)
        for root in {find(label) for label in parent}:
            planes[root], ratios[root], _ = g.planes.fit(index[root])
        for label in list(planes):
            if find(label) != label:
                del planes[label], ratios[label]
    return merges


def _pixel_filtering_eq8(regions: _Regions, g: _PriorGeometry, o: SegmentationOptions) -> int:
    """Pixel filtering (eq. 8): boundary pixels join a neighbouring reliable (r >= kappa) planar
    region when they lie within delta of its plane with a smooth normal (Phi >= phi); returns
    the number of pixels that joined."""
    if not regions.planes:
        return 0
    h, w = g.shape
    labels = regions.labels
    size = regions.next_label + 1
    plane_table = np.full((size, 4), np.nan)
    reliable = np.zeros(size, bool)
    for label, plane in regions.planes.items():
        plane_table[label] = plane
        reliable[label] = regions.ratios[label] >= o.min_inlier_ratio
    flat_points = g.points.reshape(-1, 3)
    z = flat_points[:, 2]
    smooth = g.phi >= o.normal_similarity
    # Eq. 8's distance is measured on the depth prior, which is wrong exactly where a boundary
    # pixel's side is in doubt: a monocular prior's crease lands pixels away from the true one,
    # and those pixels lie on the other side's plane. Their normals still point the other way,
    # and Phi alone misses a turn blurred over more than its search. On the suite with
    # simulated priors, fewer of the pixels filtering adds lie off their region's true plane
    # with this check.
    check_normal = g.normals is not None and o.filter_by_normal
    # Eq. 8 takes a pixel adjacent to a region; repeating it lets filtering cross a band of
    # edge pixels, but a textured patch is a wide band, and deep inside it nothing but the
    # prior vouches for a pixel's side. Three steps (Phi's search) reach across a Roberts edge;
    # on the same suite, twenty added more of the image, and more of it off its region's true
    # plane.
    filtered = 0
    for _ in range(o.filter_iterations):
        changed = 0
        # Only boundary pixels (label 0). Letting the pixels of small or poorly fitted regions
        # join too folded textured fragments into the large regions around them and lowered
        # the mean F1 at 2 cm (800x600 suite, simulated priors).
        candidate = labels == 0
        for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            neighbour = _shift(labels, dy, dx, 0)
            m = candidate & reliable[neighbour] & g.valid & smooth.reshape(h, w)
            if not m.any():
                continue
            pix = np.flatnonzero(m)
            lab = neighbour.ravel()[pix]
            pl = plane_table[lab]
            dist = np.abs((flat_points[pix] * pl[:, :3]).sum(axis=1) + pl[:, 3]) / (
                z[pix] * o.distance_unit
            )
            join = dist <= o.filter_distance
            if check_normal:
                join &= np.abs((g.normals[pix] * pl[:, :3]).sum(axis=1)) >= o.normal_similarity
            if join.any():
                labels.ravel()[pix[join]] = lab[join]
                candidate.ravel()[pix[join]] = False
                changed += int(join.sum())
        filtered += changed
        if changed == 0:
            break
    return filtered


def _renumbered(regions: _Regions, splits: int, merges: int, filtered: int) -> Segmentation:
    """0 for boundaries, regions 1..R; planes indexed by the new labels."""
    labels = regions.labels
    used = np.unique(labels[labels > 0])
    lut = np.zeros(max(regions.next_label, int(labels.max())) + 1, np.int32)
    lut[used] = np.arange(1, used.size + 1, dtype=np.int32)
    out_planes = np.full((used.size + 1, 4), np.nan)
    out_ratio = np.zeros(used.size + 1)
    for label, plane in regions.planes.items():
        if label < lut.size and lut[label] > 0:
            out_planes[lut[label]] = plane
            out_ratio[lut[label]] = regions.ratios[label]
    return Segmentation(
        labels=lut[labels],
        planes=out_planes,
        inlier_ratio=out_ratio,
        splits=splits,
        merges=merges,
        filtered=filtered,
    )


def segment(
    edges: np.ndarray,
    depth: np.ndarray,
    normal: np.ndarray | None,
    K: np.ndarray,
    depth_range: tuple[float, float],
    options: SegmentationOptions | None = None,
    depth_valid: np.ndarray | None = None,
    normal_from_depth: bool = False,
) -> Segmentation:
    """Homogeneous regions of one view from its edge map, depth prior and (optional) normal prior:
    dispersed regions and their planes, then erosion (eq. 6), dilation (eq. 7) and pixel
    filtering (eq. 8), each as its option switches it.

    ``normal_from_depth``: the normals were computed from this depth prior (``from_depth``), so
    they already turn at its steps; Phi is then eq. 5 alone, without the depth-edge rule."""
    o = options or SegmentationOptions()
    h, w = edges.shape
    if depth.shape != (h, w) or (normal is not None and normal.shape != (h, w, 3)):
        raise ValueError(
            f"edges {edges.shape}, depth {depth.shape} and normals "
            f"{None if normal is None else normal.shape} must share one image size"
        )
    geometry = _prior_geometry(depth, normal, K, depth_range, o, depth_valid, normal_from_depth)
    regions = _dispersed_regions(edges, geometry, o)
    splits = _erosion_eq6(regions, geometry, o) if o.erosion else 0
    merges = _dilation_eq7(regions, geometry, o) if o.dilation else 0
    filtered = _pixel_filtering_eq8(regions, geometry, o) if o.filtering else 0
    return _renumbered(regions, splits, merges, filtered)
