"""Deformable PatchMatch's anchors (``_anchors.pyx``, eq. 9 and 12): the search, area
maximisation, the anchor plane and the coplanar rule."""

import numpy as np
import pytest

from dvpmvs.patchmatch import _anchors
from dvpmvs.patchmatch.estimator import ANCHOR_SEARCH_START
from tests.plane_scenes import K, plane_scene

# Also run on the other Pythons `make test` checks (scripts/other_pythons.py).
pytestmark = pytest.mark.smoke


def test_anchors_never_cross_a_region_border():
    rng = np.random.default_rng(3)
    h, w = 90, 120
    # Regions: 4 vertical stripes and a disc, boundary pixels (label 0) between the stripes.
    labels = np.repeat((np.arange(w) // 30 + 1)[None, :], h, axis=0).astype(np.int32)
    labels[:, 29::30] = 0
    rows, cols = np.mgrid[0:h, 0:w]
    labels[(rows - 45) ** 2 + (cols - 60) ** 2 < 15**2] = 9
    strong = (rng.random((h, w)) < 0.05).astype(np.uint8)
    anchors = _patchmatch_find_anchors(strong, labels, reach=0.5)
    found = anchors >= 0
    assert found.sum() > 10_000  # the search does find anchors
    pix_rows, pix_cols, sector = np.nonzero(found)
    q = anchors[found]
    q_rows, q_cols = q // w, q % w
    assert np.array_equal(labels[q_rows, q_cols], labels[pix_rows, pix_cols])  # eq. 9
    assert strong[q_rows, q_cols].all() and not strong[pix_rows, pix_cols].any()
    assert not found[labels == 0].any()  # boundary pixels get none
    # Each anchor lies in its own sector (within the +-15 degree search fan) and beyond the minimum distance.
    dr, dc = q_rows - pix_rows, q_cols - pix_cols
    angle = np.degrees(np.arctan2(dr, dc)) - 45.0 * sector
    angle = (angle + 180) % 360 - 180
    assert np.abs(angle).max() <= 15.0 + np.degrees(np.arctan2(1, ANCHOR_SEARCH_START))
    assert (np.hypot(dr, dc) >= ANCHOR_SEARCH_START - 0.5).all()
    # Without labels (w/o Agn) the same search crosses the borders.
    free = _patchmatch_find_anchors(strong, None, reach=0.5)
    fr, fc, _ = np.nonzero(free >= 0)
    fq = free[free >= 0]
    assert (labels[fq // w, fq % w] != labels[fr, fc]).any()


def test_anchor_search_crosses_a_large_textureless_region():
    # A 300x400 region strong only along its border: the centre's anchors lie 150-200 px away,
    # found with the default reach (the whole image).
    h, w = 300, 400
    strong = np.zeros((h, w), np.uint8)
    strong[:3], strong[-3:], strong[:, :3], strong[:, -3:] = 1, 1, 1, 1
    labels = np.ones((h, w), np.int32)
    anchors = _patchmatch_find_anchors(strong, labels)
    centre = anchors[150, 200]
    assert (centre >= 0).all()
    rows, cols = centre // w, centre % w
    assert strong[rows, cols].all() and np.hypot(rows - 150, cols - 200).min() >= 140
    # A reach of 10 % of the side (40 px) finds nothing there.
    short = _patchmatch_find_anchors(strong, labels, reach=0.1)
    assert (short[150, 200] < 0).all()


_SEARCH_TURNS = (
    0.0,
    1.0 / 3.0,
    -1.0 / 3.0,
)  # a sector's three lines, in 45-degree units, centre first


def _weak_region_pixels(strong, labels):
    """The pixels the anchor search serves: weak ones inside a region, with their region."""
    for row, col in np.ndindex(*strong.shape):
        own = labels[row, col] if labels is not None else 1
        if not strong[row, col] and own > 0:
            yield row, col, own


def _search_line_point(row, col, sector, turn, r):
    """The pixel r px from (row, col) on one of a sector's search lines, rounded as the kernel does."""
    angle = (sector + turn) * np.pi / 4.0
    return row + int(np.floor(r * np.sin(angle) + 0.5)), col + int(
        np.floor(r * np.cos(angle) + 0.5)
    )


def _anchor_on_line(strong, labels, own, row, col, sector, turn, r):
    """That pixel, if it may be an anchor of a pixel of region ``own``."""
    qr, qc = _search_line_point(row, col, sector, turn, r)
    h, w = strong.shape
    if 0 <= qr < h and 0 <= qc < w and strong[qr, qc] and (labels is None or labels[qr, qc] == own):
        return qr, qc
    return None


def _reference_anchors(strong, labels, min_distance, max_distance, step):
    """The anchor walk written out plainly: every step from min_distance to max_distance along
    the 3 lines of each sector, nothing skipped."""
    h, w = strong.shape
    out = np.full((h, w, 8), -1, np.int32)
    for row, col, own in _weak_region_pixels(strong, labels):
        for a in range(8):
            for r in range(min_distance, max_distance + 1, step):
                hit = next(
                    (
                        q
                        for q in (
                            _anchor_on_line(strong, labels, own, row, col, a, turn, r)
                            for turn in _SEARCH_TURNS
                        )
                        if q is not None
                    ),
                    None,
                )
                if hit is not None:
                    out[row, col, a] = hit[0] * w + hit[1]
                    break
    return out


@pytest.mark.parametrize("with_labels", [True, False])
def test_anchor_search_finds_what_the_plain_walk_finds(with_labels):
    # The kernel walks only the stretch of each line inside the bounding box of the region's
    # strong pixels; it must find exactly the anchors of the walk over the whole distance,
    # including regions without strong pixels, regions wrapping around others and the image border.
    rng = np.random.default_rng(11)
    h, w = 37, 53
    rows, cols = np.mgrid[0:h, 0:w]
    labels = (1 + (cols // 13) + 5 * (rows // 19)).astype(np.int32)
    labels[
        ((rows - 18) ** 2 + (cols - 26) ** 2 > 8**2) & ((rows - 18) ** 2 + (cols - 26) ** 2 < 12**2)
    ] = 20  # a ring
    labels[rng.random((h, w)) < 0.03] = 0
    strong = (rng.random((h, w)) < 0.04).astype(np.uint8)
    strong[labels == 2] = 0  # a region with no strong pixel at all
    labels = labels if with_labels else None
    expected = _reference_anchors(strong, labels, 3, max(h, w), 2)
    assert (expected >= 0).sum() > 1000
    assert np.array_equal(_patchmatch_find_anchors(strong, labels), expected)


def _reference_area_anchors(strong, labels, min_distance, max_distance, step):
    """Paper eq. 12 written out plainly: the first strong pixel on each of a sector's three lines
    (walked over the whole distance), the nearest of them to start with, then each sector in turn
    takes the candidate c maximising (c - p) x (next anchor - previous anchor), until no
    change."""
    h, w = strong.shape
    out = np.full((h, w, 8), -1, np.int32)
    for row, col, own in _weak_region_pixels(strong, labels):
        candidates = [[None] * 3 for _ in range(8)]
        nearest = [None] * 8
        for a in range(8):
            hits = []
            for k, turn in enumerate(_SEARCH_TURNS):
                for r in range(min_distance, max_distance + 1, step):
                    q = _anchor_on_line(strong, labels, own, row, col, a, turn, r)
                    if q is not None:
                        candidates[a][k] = q
                        hits.append((r, k))
                        break
            if hits:
                r, k = min(hits)
                nearest[a] = candidates[a][k]
        anchors = list(nearest)
        for _ in range(4):
            changed = False
            for a in range(8):
                if anchors[a] is None:
                    continue
                after = [(a + m) % 8 for m in range(1, 8) if anchors[(a + m) % 8] is not None]
                if not after or after[0] == after[-1]:
                    continue
                nxt, prev = anchors[after[0]], anchors[after[-1]]
                ur, uc = nxt[0] - prev[0], nxt[1] - prev[1]

                def gain(q):
                    return (q[1] - col) * ur - (q[0] - row) * uc

                best = anchors[a]
                for q in candidates[a]:
                    if q is not None and gain(q) > gain(best):
                        best = q
                if best != anchors[a]:
                    anchors[a], changed = best, True
            if not changed:
                break
        out[row, col] = [-1 if q is None else q[0] * w + q[1] for q in anchors]
    return out


def _polygon_areas(anchors, w):
    """Twice the signed area of each pixel's anchor polygon (sectors in order, empty ones skipped)."""
    total = np.zeros(anchors.shape[:2], np.int64)
    for row, col in zip(*np.nonzero((anchors >= 0).sum(axis=2) >= 3)):
        ring = [q for q in anchors[row, col] if q >= 0]
        x = np.array([q % w for q in ring]) - col
        y = np.array([q // w for q in ring]) - row
        total[row, col] = int(np.sum(x * np.roll(y, -1) - y * np.roll(x, -1)))
    return total


@pytest.mark.parametrize("with_labels", [True, False])
def test_area_maximisation_grows_the_anchor_polygon(with_labels):
    rng = np.random.default_rng(12)
    h, w = 37, 53
    rows, cols = np.mgrid[0:h, 0:w]
    labels = (1 + (cols // 17) + 4 * (rows // 19)).astype(np.int32)
    labels[rng.random((h, w)) < 0.03] = 0
    strong = (rng.random((h, w)) < 0.05).astype(np.uint8)
    labels = labels if with_labels else None
    nearest = _patchmatch_find_anchors(strong, labels)
    area = _patchmatch_find_anchors(strong, labels, area_maximisation=True)
    assert np.array_equal(area, _reference_area_anchors(strong, labels, 3, max(h, w), 2))
    # The same sectors are filled; anchors move in a share of them, and every move grows the
    # polygon, so no pixel's polygon shrinks and many grow.
    assert np.array_equal(area >= 0, nearest >= 0)
    moved = (area != nearest).any(axis=2)
    assert 0.05 < moved[(nearest >= 0).sum(axis=2) >= 3].mean() < 1.0
    before, after = _polygon_areas(nearest, w), _polygon_areas(area, w)
    assert (after >= before).all() and (after[moved] > before[moved]).all()
    # With fewer than three anchors there is no polygon: the nearest anchors stay.
    few = (nearest >= 0).sum(axis=2) < 3
    assert np.array_equal(area[few], nearest[few])


def _chord_pixel():
    """Pixel (50, 50) of a 101x101 strong map. Sector 0 (east) holds a strong pixel 6 px away on
    its centre line and one 20 px away on its +15 degree line; sectors 1 and 7 hold one each,
    10 px away at +-45 degrees, and sector 4 one 10 px west. The neighbours' chord runs at column
    57: the nearest candidate (column 56) lies inside it, the far one (column 69) beyond it.
    Returns the strong map, the near and the far candidate."""

    def on_line(sector, turn, r):
        return _search_line_point(50, 50, sector, turn, r)

    strong = np.zeros((101, 101), np.uint8)
    near, far = on_line(0, 0.0, 6), on_line(0, 1.0 / 3.0, 20)
    for q in (near, far, on_line(1, 0.0, 10), on_line(7, 0.0, 10), on_line(4, 0.0, 10)):
        strong[q] = 1
    assert near == (50, 56) and far == (55, 69)
    return strong, near, far


def test_area_maximisation_takes_the_candidate_beyond_its_neighbours_chord():
    # _chord_pixel's far candidate grows the anchors' polygon; the near one does not.
    strong, near, far = _chord_pixel()
    nearest = _patchmatch_find_anchors(strong, None, step=1)[50, 50]
    area = _patchmatch_find_anchors(strong, None, area_maximisation=True, step=1)[50, 50]
    assert nearest[0] == near[0] * 101 + near[1]
    assert area[0] == far[0] * 101 + far[1]
    assert (nearest >= 0).sum() == 4
    assert np.array_equal(area[1:], nearest[1:])


def _patchmatch_find_anchors(strong, labels, area_maximisation=False, reach=1.0, step=2):
    from dvpmvs.patchmatch.estimator import find_anchors

    return find_anchors(strong, labels, area_maximisation, 2, reach, step)


_AROUND = [(20, 40), (20, 50), (30, 52), (40, 50), (40, 40), (40, 30), (30, 28), (20, 30)]


def _anchors_around_pixel(shape):
    """(H, W, 8) anchors: pixel (30, 40) has the 8 pixels of ``_AROUND``, every other none."""
    anchors = np.full((*shape, 8), -1, np.int32)
    for a, (r, c) in enumerate(_AROUND):
        anchors[30, 40, a] = r * shape[1] + c
    return anchors


def test_anchor_plane_interpolates_the_anchors_plane_and_ignores_an_outlier():
    _, plane_depth, normals = plane_scene()
    h, w = plane_depth.shape
    depth = plane_depth.copy()
    anchors = _anchors_around_pixel((h, w))
    around = _AROUND
    # Pixel (30, 40) with anchors around it on the plane; one (to the right) 20 % off it.
    depth[30, 52] *= 1.2
    # Pixel (5, 5): three anchors, all to its right and below (it lies outside their triangle).
    for a, (r, c) in enumerate([(10, 10), (10, 20), (20, 10)]):
        anchors[5, 5, a] = r * w + c
    fit_depth = np.zeros((h, w), np.float32)
    fit_normal = np.zeros((h, w, 3), np.float32)
    _anchors.fit_anchor_planes(depth, anchors, K, fit_depth, fit_normal, 0.01, 4, 2)
    assert fit_depth[30, 40] == pytest.approx(plane_depth[30, 40], rel=1e-4)
    np.testing.assert_allclose(fit_normal[30, 40], normals[30, 40], atol=1e-3)
    assert fit_depth[5, 5] == 0  # no triangle contains it: no extrapolation
    assert (fit_depth[anchors[..., 0] < 0] == 0).all()  # no anchors, no plane
    # With five of them filtered out (depth 0), three anchors are left: below min_inliers 4.
    for r, c in around[:5]:
        depth[r, c] = 0
    _anchors.fit_anchor_planes(depth, anchors, K, fit_depth, fit_normal, 0.01, 4, 2)
    assert fit_depth[30, 40] == 0
    _anchors.fit_anchor_planes(depth, anchors, K, fit_depth, fit_normal, 0.01, 3, 2)
    assert fit_depth[30, 40] == 0  # and their triangle (all on the left) does not contain the pixel


def test_coplanar_rule_drops_anchors_off_the_pixels_plane():
    _, plane_depth, _ = plane_scene()
    h, w = plane_depth.shape
    depth = plane_depth.copy()
    anchors = _anchors_around_pixel((h, w))
    # Pixel (30, 40): six anchors on the plane, two (slots 2 and 5) on a surface 20 % nearer,
    # as anchors across a depth edge would be.
    depth[30, 52] *= 0.8
    depth[40, 30] *= 0.8
    # Pixel (10, 60): four anchors on four different surfaces (no plane agreed with by 4).
    for a, ((r, c), f) in enumerate(
        zip([(5, 60), (10, 66), (15, 60), (10, 54)], [1.0, 0.7, 1.3, 0.5])
    ):
        anchors[10, 60, a] = r * w + c
        depth[r, c] = plane_depth[r, c] * f
    before = anchors.copy()
    _anchors.keep_coplanar_anchors(depth, anchors, K, 0.01, 4, 2)
    expected = before[30, 40].copy()
    expected[[2, 5]] = -1
    np.testing.assert_array_equal(anchors[30, 40], expected)
    assert (anchors[10, 60] == -1).all()
    # Every other pixel is untouched (it had no anchors).
    untouched = np.ones((h, w), bool)
    untouched[30, 40] = untouched[10, 60] = False
    np.testing.assert_array_equal(anchors[untouched], before[untouched])
    # With min_inliers 7 the six coplanar anchors are not enough either.
    anchors = before.copy()
    _anchors.keep_coplanar_anchors(depth, anchors, K, 0.01, 7, 2)
    assert (anchors[30, 40] == -1).all()
