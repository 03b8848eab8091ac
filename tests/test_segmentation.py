"""The depth-normal-edge aligned prior on constructed depth / normal / edge triples."""

from dataclasses import replace

import cv2
import numpy as np
import pytest

from dvpmvs import registry
from dvpmvs.priors import PriorContext
from dvpmvs.segmentation import SegmentationOptions, normal_similarity, segment

# Also run on the other Pythons `make test` checks (scripts/other_pythons.py).
pytestmark = pytest.mark.smoke

K = np.array([[300.0, 0, 100], [0, 300.0, 75], [0, 0, 1]])
H, W = 150, 200
ROWS, COLS = np.mgrid[0:H, 0:W].astype(np.float64)
RX, RY = (COLS - K[0, 2]) / K[0, 0], (ROWS - K[1, 2]) / K[1, 1]


def _plane_depth(a: float, b: float, c: float = 3.0) -> np.ndarray:
    """Depth of the plane z = c + a X + b Y along every pixel's ray."""
    return (c / (1.0 - a * RX - b * RY)).astype(np.float32)


def normals_from_depth(depth, K, sigma):
    """The ``from_depth`` normal prior of ``depth``, as a dense run builds it (through the registry)."""
    provider = registry.create("normal_prior", {"name": "from_depth", "sigma": sigma})
    return provider(PriorContext("view", np.zeros(depth.shape, np.float32), K, (1.0, 10.0)), depth)


def _crease():
    """Two planes meeting at a 90-degree crease along column 100, no image edge anywhere."""
    depth = np.where(COLS < 100, _plane_depth(1.0, 0.0), _plane_depth(-1.0, 0.0)).astype(np.float32)
    return np.zeros((H, W), bool), depth, normals_from_depth(depth, K, 0)


def _cut_plane(edge_width: int = 3):
    """One slanted plane crossed by a texture edge (a vertical band of edge pixels)."""
    depth = _plane_depth(0.3, 0.2)
    edges = np.zeros((H, W), bool)
    edges[:, 98 : 98 + edge_width] = True
    return edges, depth, normals_from_depth(depth, K, 0)


def test_crease_without_image_edge_ends_in_two_regions():
    edges, depth, normal = _crease()
    seg = segment(edges, depth, normal, K, (1.0, 8.0))
    assert seg.splits >= 1
    labels = seg.labels
    assert labels.max() == 2
    # Each side of the crease is one region (a few pixels at the crease itself may go either way).
    left, right = labels[:, :96], labels[:, 104:]
    assert np.unique(left).size == 1 and np.unique(right).size == 1 and left[0, 0] != right[0, 0]
    # The two planes were recovered: normals (1, 0, -1)/sqrt2 and (-1, 0, -1)/sqrt2.
    normals = seg.planes[1:, :3]
    assert np.allclose(np.sort(normals[:, 0]), [-np.sqrt(0.5), np.sqrt(0.5)], atol=0.02)


def test_erosion_divides_at_the_normals_turn_when_the_depth_prior_is_warped():
    # A monocular depth prior's scale error grows across the image: both sides are still
    # planar-looking but their planes no longer meet at the crease. Divided where the two
    # planes meet, the pieces' boundary misses the turn of the normals (Phi sees none there)
    # and the crease stays one region; divided along the normals, it splits at the crease.
    edges, depth, normal = _crease()
    warped = (depth * (1 + 0.5 * ((COLS - 60) / W) ** 2)).astype(np.float32)
    seg = segment(edges, warped, normal, K, (1.0, 8.0))
    assert seg.splits == 1 and seg.labels.max() == 2
    left, right = seg.labels[:, :97], seg.labels[:, 103:]
    assert np.unique(left).size == 1 and np.unique(right).size == 1 and left[0, 0] != right[0, 0]
    by_planes = segment(
        edges, warped, normal, K, (1.0, 8.0), SegmentationOptions(split_by_normals=False)
    )
    assert by_planes.splits == 0 and by_planes.labels.max() == 1
    # Normals derived from the depth prior turn where its planes meet: the plane division stays.
    from_depth = segment(edges, warped, normal, K, (1.0, 8.0), normal_from_depth=True)
    assert from_depth.splits == 0 and from_depth.labels.max() == 1


def test_crease_stays_one_region_without_erosion():
    edges, depth, normal = _crease()
    seg = segment(
        edges, depth, normal, K, (1.0, 8.0), SegmentationOptions(erosion=False, dilation=False)
    )
    assert seg.labels.max() == 1 and seg.splits == 0


def test_plane_cut_by_a_texture_edge_merges_into_one_region():
    edges, depth, normal = _cut_plane()
    seg = segment(edges, depth, normal, K, (1.0, 8.0))
    assert seg.merges == 1
    assert seg.labels.max() == 1
    # Pixel filtering gave the edge band to the region: no boundary pixel is left.
    assert (seg.labels > 0).all() and seg.filtered == 3 * H


def test_filtering_reaches_filter_iterations_pixels_into_a_wide_band():
    # A 10-px band of edge pixels (cols 98-107) between two regions of one plane: each side
    # takes 3 columns, the middle 4 stay boundary; 20 steps fill the band.
    edges, depth, normal = _cut_plane(edge_width=10)
    seg = segment(edges, depth, normal, K, (1.0, 8.0))
    assert seg.filtered == 6 * H
    assert (
        (seg.labels[:, 101:105] == 0).all()
        and (seg.labels[:, 98:101] > 0).all()
        and (seg.labels[:, 105:108] > 0).all()
    )
    deep = segment(edges, depth, normal, K, (1.0, 8.0), SegmentationOptions(filter_iterations=20))
    assert deep.filtered == 10 * H and (deep.labels > 0).all()


def test_filtering_takes_boundary_pixels_but_not_small_regions():
    # A 10x10 textured fragment (outlined by edge pixels, under min_region) on the plane: its
    # outline joins the plane's region, the fragment keeps a region of its own.
    edges, depth, normal = _cut_plane()
    edges[30:42, 30] = edges[30:42, 41] = edges[30, 30:42] = edges[41, 30:42] = True
    seg = segment(edges, depth, normal, K, (1.0, 8.0))
    fragment = seg.labels[31:41, 31:41]
    assert np.unique(fragment).size == 1 and fragment[0, 0] > 0
    assert fragment[0, 0] != seg.labels[0, 0]
    assert (seg.labels[30, 30:42] == seg.labels[0, 0]).all()  # the outline was filtered in


def test_filtering_stops_where_the_normal_prior_leaves_the_plane():
    # A crease at column 100 under a 16-px edge band (cols 95-110). The monocular depth prior
    # puts the crease 12 px late (the left plane runs on to col 111) and the normal prior turns
    # gradually (blurred), so Phi sees no sharp turn inside the band. Judged by the prior depth
    # alone, the band's pixels right of the crease lie on the left region's plane and join it;
    # their normals say they do not.
    left, right = _plane_depth(1.0, 0.0), _plane_depth(-1.0, 0.0)
    normal = cv2.GaussianBlur(
        normals_from_depth(np.where(COLS < 100, left, right).astype(np.float32), K, 0), (0, 0), 3.0
    )
    normal /= np.linalg.norm(normal, axis=2, keepdims=True)
    prior = np.where(COLS < 112, left, right).astype(np.float32)
    edges = np.zeros((H, W), bool)
    edges[:, 95:111] = True

    def last_left_column(seg):
        return max(int(np.flatnonzero(row == seg.labels[0, 0]).max()) for row in seg.labels)

    # Filtering may reach 20 pixels deep here, so that only the normal check can stop it.
    deep = SegmentationOptions(filter_iterations=20)
    checked = segment(edges, prior, normal, K, (1.0, 8.0), deep)
    assert checked.filtered > 0 and last_left_column(checked) <= 103
    by_depth_only = segment(
        edges, prior, normal, K, (1.0, 8.0), replace(deep, filter_by_normal=False)
    )
    assert last_left_column(by_depth_only) >= 106
    # Normals derived from the depth prior are no second opinion: the check is off with them.
    derived = segment(edges, prior, normal, K, (1.0, 8.0), deep, normal_from_depth=True)
    unchecked = segment(
        edges,
        prior,
        normal,
        K,
        (1.0, 8.0),
        replace(deep, filter_by_normal=False),
        normal_from_depth=True,
    )
    assert derived.filtered == unchecked.filtered and np.array_equal(
        derived.labels, unchecked.labels
    )


def test_ablations_leave_the_texture_edge_split_or_unfiltered():
    edges, depth, normal = _cut_plane()
    no_dilation = segment(edges, depth, normal, K, (1.0, 8.0), SegmentationOptions(dilation=False))
    assert no_dilation.labels.max() == 2
    no_filter = segment(edges, depth, normal, K, (1.0, 8.0), SegmentationOptions(filtering=False))
    assert no_filter.labels.max() == 1 and (no_filter.labels[:, 98:101] == 0).all()


def test_parallel_planes_with_a_depth_step_do_not_merge():
    # Same normal on both sides (a monocular normal prior would not see the step), 15 % deeper
    # on the right: Psi's depth term keeps them apart.
    depth = np.where(COLS < 98, _plane_depth(0.0, 0.0, 3.0), _plane_depth(0.0, 0.0, 3.45)).astype(
        np.float32
    )
    edges = np.zeros((H, W), bool)
    edges[:, 98:101] = True
    normal = np.zeros((H, W, 3), np.float32)
    normal[..., 2] = -1
    seg = segment(edges, depth, normal, K, (1.0, 8.0))
    assert seg.merges == 0 and seg.labels.max() == 2


def test_recessed_pane_a_blurred_step_away_stays_apart():
    # A window pane 1.5 % of the depth behind the wall, outlined by its frame's image edge, with
    # the wall's normal and a depth prior blurred like a monocular one: no pixel's depth changes
    # by epsilon (the step, 0.0064 of the depth range, spreads over ~6 pixels), so only Psi's
    # depth term can keep the pane out of the wall: it merges parallel planes up to half a
    # distance unit (1 % of depth) apart.
    recess = (ROWS >= 40) & (ROWS < 110) & (COLS >= 60) & (COLS < 140)
    depth = np.where(recess, _plane_depth(0.0, 0.0, 3.045), _plane_depth(0.0, 0.0, 3.0))
    depth = cv2.GaussianBlur(depth.astype(np.float32), (0, 0), 2.5)
    square = np.ones((3, 3), np.uint8)
    frame = cv2.dilate(recess.astype(np.uint8), square) > cv2.erode(recess.astype(np.uint8), square)
    normal = np.zeros((H, W, 3), np.float32)
    normal[..., 2] = -1
    seg = segment(frame, depth, normal, K, (1.0, 8.0))
    assert seg.merges == 0 and seg.labels.max() == 2
    assert seg.labels[75, 100] != seg.labels[5, 5] and seg.labels[75, 100] > 0
    shallow = np.where(recess, _plane_depth(0.0, 0.0, 3.015), _plane_depth(0.0, 0.0, 3.0))
    shallow = cv2.GaussianBlur(shallow.astype(np.float32), (0, 0), 2.5)
    assert (
        segment(frame, shallow, normal, K, (1.0, 8.0)).merges == 1
    )  # 0.5 %: one surface to the prior


def test_recessed_pane_under_a_warped_prior_stays_apart_by_the_step_at_its_seam():
    # The same pane, 1.5 % behind its wall, under a prior whose scale grows away from the pane
    # by up to 2 % (a monocular prior's smooth scale error). The wall's plane, fitted to all of
    # it, lies deeper than the wall next to the pane, and meets the pane's plane there within
    # 1 % of depth: the planes alone merge them. The prior next to the frame keeps the step.
    recess = (ROWS >= 40) & (ROWS < 110) & (COLS >= 60) & (COLS < 140)
    square = np.ones((3, 3), np.uint8)
    frame = cv2.dilate(recess.astype(np.uint8), square) > cv2.erode(recess.astype(np.uint8), square)
    normal = np.zeros((H, W, 3), np.float32)
    normal[..., 2] = -1
    r2 = (ROWS - 75) ** 2 + (COLS - 100) ** 2
    scale = 1 + 0.02 * r2 / r2.max()
    for behind, apart in (
        (3.045, True),
        (3.0, False),
    ):  # a recessed pane; a frame painted on the wall
        depth = (
            np.where(recess, _plane_depth(0.0, 0.0, behind), _plane_depth(0.0, 0.0, 3.0)) * scale
        )
        depth = cv2.GaussianBlur(depth.astype(np.float32), (0, 0), 2.5)
        seg = segment(frame, depth, normal, K, (1.0, 8.0))
        assert seg.merges == (0 if apart else 1) and seg.labels.max() == (2 if apart else 1)
        assert (
            segment(frame, depth, normal, K, (1.0, 8.0), SegmentationOptions(seam_band=0)).merges
            == 1
        )


def _step():
    """Two parallel planes, the right one 15 % deeper, no image edge, one normal everywhere."""
    depth = np.where(COLS < 100, _plane_depth(0.0, 0.0, 3.0), _plane_depth(0.0, 0.0, 3.45)).astype(
        np.float32
    )
    normal = np.zeros((H, W, 3), np.float32)
    normal[..., 2] = -1
    return np.zeros((H, W), bool), depth, normal


def test_depth_step_without_image_edge_splits_although_the_normals_agree():
    # The normals add to the depth-edge rule: a step the normal prior cannot see still splits.
    edges, depth, normal = _step()
    for normals in (normal, None):
        seg = segment(
            edges,
            depth,
            normals,
            K,
            (1.0, 8.0),
            SegmentationOptions(use_normals=normals is not None),
        )
        assert seg.splits >= 1 and seg.labels.max() == 2
        left, right = seg.labels[:, :96], seg.labels[:, 104:]
        assert (
            np.unique(left).size == 1 and np.unique(right).size == 1 and left[0, 0] != right[0, 0]
        )


def test_depth_prior_folded_where_the_normals_agree_stays_one_region():
    # A flat wall under a monocular depth prior whose scale error folds it: the prior shows two
    # planes 45 degrees apart with a step between them, the independent normals one plane. The
    # normals show no turn, so only a step could divide it, and a step's sides are parallel.
    _, _, normal = _step()
    folded = np.where(COLS < 100, _plane_depth(0.0, 0.0, 3.0), _plane_depth(1.0, 0.0, 3.45)).astype(
        np.float32
    )
    edges = np.zeros((H, W), bool)
    seg = segment(edges, folded, normal, K, (1.0, 8.0))
    assert seg.splits == 0 and seg.labels.max() == 1
    unlimited = segment(
        edges, folded, normal, K, (1.0, 8.0), SegmentationOptions(max_step_tilt=180)
    )
    assert unlimited.splits == 1 and unlimited.labels.max() == 2
    # Without the normal prior the depth prior is all there is, and it shows two planes.
    depth_only = segment(edges, folded, None, K, (1.0, 8.0), SegmentationOptions(use_normals=False))
    assert depth_only.splits == 1 and depth_only.labels.max() == 2


def test_normals_derived_from_the_depth_take_no_depth_edge_rule():
    # A steep but smooth plane: around the texture edge its normalised depth changes faster than
    # epsilon per pixel, so the depth-edge rule keeps the two sides apart and the edge band
    # unfiltered; normals from the same depth see one plane, and the sides merge.
    edges, _, _ = _cut_plane()
    depth = _plane_depth(2.0, 0.0)
    normal = normals_from_depth(depth, K, 0)
    depth_range = (1.0, 4.0)  # at the texture edge the depth grows 2 cm a pixel: 0.0067 normalised
    alone = segment(edges, depth, normal, K, depth_range, normal_from_depth=True)
    assert alone.merges == 1 and alone.labels.max() == 1 and (alone.labels > 0).all()
    combined = segment(edges, depth, normal, K, depth_range)
    assert combined.merges == 0 and (combined.labels == 0).any()


def test_depth_only_mode_uses_the_depth_gradient():
    edges, depth, _ = _cut_plane()
    seg = segment(edges, depth, None, K, (1.0, 8.0), SegmentationOptions(use_normals=False))
    assert seg.labels.max() == 1


def test_normal_similarity_sees_a_crease_from_a_few_pixels_away():
    _, _, normal = _crease()
    phi = normal_similarity(normal, 3)
    assert phi[10:-10, 90].min() > 0.99  # far from the crease (and the image border)
    assert phi[10:-10, 98].max() < 0.1  # 2-3 pixels from the crease, the search reaches across


def test_bad_options_and_shapes_are_refused():
    with pytest.raises(ValueError, match="min_region"):
        SegmentationOptions(min_region=1)
    with pytest.raises(ValueError, match="filter_iterations"):
        SegmentationOptions(filter_iterations=0)
    with pytest.raises(ValueError, match="seam_band"):
        SegmentationOptions(seam_band=-1)
    with pytest.raises(ValueError, match="max_step_tilt"):
        SegmentationOptions(max_step_tilt=0)
    edges, depth, normal = _crease()
    with pytest.raises(ValueError, match="share one image size"):
        segment(edges[:, :10], depth, normal, K, (1.0, 8.0))
    assert replace(SegmentationOptions(), erosion=False).erosion is False


def test_segmentation_options_name_unknown_keys():
    from dvpmvs.segmentation import SegmentationOptions

    with pytest.raises(ValueError, match="unknown segmentation option.*etta.*known:.*eta"):
        SegmentationOptions.from_mapping({"etta": 100})
