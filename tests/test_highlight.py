"""Highlight perception (paper section 3.5): the providers on constructed images, the multi-view
evidence, the estimator's rules, the stage in the dense pipeline and its evaluation."""

import json

import cv2
import numpy as np
import pytest

from dvpmvs import registry
from dvpmvs.highlight import check_highlight_output, multiview_highlight
from dvpmvs.patchmatch import PatchMatchOptions, Problem, ViewData, _patchmatch, estimate
from dvpmvs.patchmatch.estimator import _kernel_params, _Level, _matching_images
from dvpmvs.priors import PriorContext, PriorError
from tests.plane_scenes import K, plane_scene


def _lobe_image(size=(120, 160), peak=0.45, albedo=(0.55, 0.3, 0.2), seed=0):
    """A Lambertian colour gradient with a white specular lobe (dichromatic: the lobe adds the
    same amount to every channel). Returns rgb, diffuse rgb and the specular term."""
    h, w = size
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float32)
    shading = 0.5 + 0.45 * cols / w
    rng = np.random.default_rng(seed)
    texture = cv2.GaussianBlur(rng.random((h, w)).astype(np.float32), (0, 0), 2) * 0.3 + 0.85
    diffuse = (shading * texture)[..., None] * np.asarray(albedo, np.float32)
    specular = peak * np.exp(-((rows - 0.45 * h) ** 2 + (cols - 0.6 * w) ** 2) / (2 * 9.0**2))
    rgb = np.clip(diffuse + specular[..., None], 0, 1).astype(np.float32)
    return rgb, diffuse.astype(np.float32), specular.astype(np.float32)


def _grey(rgb):
    from dvpmvs.image import to_grey

    return to_grey(rgb)


def _context(rgb, name="v.png", root=None):
    return PriorContext(name, _grey(rgb), np.eye(3), (1.0, 2.0), rgb_loader=lambda: rgb, root=root)


def _scores(mask, specular):
    """(recall of the lobe's core, share of the mask on the lobe)."""
    core, lobe = specular >= 0.1, specular >= 0.01
    return float(mask[core].mean()), float(mask[lobe].sum() / max(mask.sum(), 1))


def test_dichromatic_finds_the_lobe_and_removes_it():
    rgb, diffuse, specular = _lobe_image()
    corrector = registry.create("highlight", {"name": "dichromatic"})
    corrected, mask = corrector(_context(rgb))
    recall, on_lobe = _scores(mask, specular)
    assert recall >= 0.88 and on_lobe >= 0.97, (recall, on_lobe)
    core = specular >= 0.1
    before = np.abs(_grey(rgb) - _grey(diffuse))[core].mean()
    after = np.abs(corrected - _grey(diffuse))[core].mean()
    assert before > 0.2 and after < 0.06, (before, after)
    # Outside the mask the image is matched as it is.
    np.testing.assert_array_equal(corrected[~mask], _grey(rgb)[~mask])


def test_threshold_finds_a_saturated_lobe_and_fills_it():
    rgb, diffuse, specular = _lobe_image(peak=1.0)
    corrected, mask = registry.create("highlight", {"name": "threshold"})(_context(rgb))
    saturated = rgb.max(axis=2) >= 0.99
    assert mask[saturated].mean() >= 0.95
    assert mask.sum() <= 3 * (specular >= 0.1).sum()
    before = np.abs(_grey(rgb) - _grey(diffuse))[saturated].mean()
    after = np.abs(corrected - _grey(diffuse))[saturated].mean()
    assert after < 0.8 * before, (before, after)  # measured 0.69: filled from the lobe's rim


def test_a_lambertian_image_has_no_highlight():
    rgb, _, _ = _lobe_image(peak=0.0)
    for name in ("dichromatic", "threshold"):
        corrected, mask = registry.create("highlight", {"name": name})(_context(rgb))
        assert mask.mean() < 0.01, name
        assert np.abs(corrected - _grey(rgb)).max() < 0.05, name


def test_file_provider_reads_masks_and_corrected_images(tmp_path):
    rgb, diffuse, specular = _lobe_image()
    (tmp_path / "masks").mkdir()
    (tmp_path / "fixed").mkdir()
    cv2.imwrite(str(tmp_path / "masks" / "v.png"), ((specular >= 0.1) * 255).astype(np.uint8))
    cv2.imwrite(
        str(tmp_path / "fixed" / "v.png"), np.round(diffuse[..., ::-1] * 255).astype(np.uint8)
    )
    provider = registry.create("highlight", {"name": "file", "path": "masks", "corrected": "fixed"})
    corrected, mask = provider(_context(rgb, root=tmp_path))
    np.testing.assert_array_equal(mask, specular >= 0.1)
    assert np.abs(corrected - _grey(diffuse)).max() < 0.01
    assert [p.name for p in provider.input_files("v.png", tmp_path)] == ["v.png", "v.png"]
    with pytest.raises(PriorError, match="no highlight mask for image w.png"):
        provider(_context(rgb, name="w.png", root=tmp_path))
    with pytest.raises(registry.PluginError, match="takes path, corrected"):
        registry.create("highlight", {"name": "file", "folder": "masks"})


def test_bad_outputs_name_the_provider_and_the_view():
    good = np.zeros((4, 5), np.float32)
    with pytest.raises(
        PriorError, match=r"provider 'mine' returned a mask of shape \(5, 4\) for view a.png"
    ):
        check_highlight_output("mine", "a.png", good, np.zeros((5, 4), bool), (4, 5))
    nan = good.copy()
    nan[1, 1] = np.nan
    with pytest.raises(PriorError, match="'mine' returned 1 NaN or infinite value.*view a.png"):
        check_highlight_output("mine", "a.png", nan, np.zeros((4, 5), bool), (4, 5))
    with pytest.raises(PriorError, match="outside \\[0, 1\\]"):
        check_highlight_output("mine", "a.png", good + 255, np.zeros((4, 5), bool), (4, 5))
    with pytest.raises(PriorError, match="NaN in the mask"):
        check_highlight_output("mine", "a.png", good, nan, (4, 5))
    maps = check_highlight_output("mine", "a.png", good, np.where(good > 0, 0.0, 0.9), (4, 5))
    assert maps.mask.dtype == bool and maps.mask.all()


def test_multiview_evidence_finds_a_highlight_that_one_view_alone_shows():
    # A plane seen by a reference and two sources; a bright blob only in the reference (a
    # highlight moves with the viewpoint) is found, and the sources' level is its diffuse level.
    problem, depth, _ = plane_scene(num_sources=2)
    ref = problem.reference
    h, w = depth.shape
    rows, cols = np.mgrid[0:h, 0:w]
    blob = 0.4 * np.exp(-((rows - 30) ** 2 + (cols - 40) ** 2) / (2 * 4.0**2))
    shiny = np.clip(ref.image + blob, 0, 1).astype(np.float32)
    sources = []
    for s in problem.sources:
        # The sources' depth maps: the plane seen from them (through the reference's depth).
        src_depth = np.zeros_like(depth)
        X = (
            np.stack([cols, rows, np.ones_like(cols)], -1).reshape(-1, 3) @ np.linalg.inv(K).T
        ) * depth.reshape(-1, 1)
        Y = X @ s.R.T + s.t
        uv = Y @ K.T
        u, v = np.round(uv[:, 0] / uv[:, 2]).astype(int), np.round(uv[:, 1] / uv[:, 2]).astype(int)
        ok = (u >= 0) & (v >= 0) & (u < w) & (v < h)
        src_depth[v[ok], u[ok]] = Y[ok, 2]
        sources.append((s.image, src_depth, s.K, s.R, s.t))
    mask, diffuse = multiview_highlight(
        shiny, depth, K, ref.R, ref.t, sources, min_excess=0.06, dilate=0, neighbourhood=0
    )
    core = blob >= 0.1
    assert mask[core].mean() > 0.9, mask[core].mean()
    assert mask[blob < 0.02].mean() < 0.02
    assert np.abs(diffuse - ref.image)[core].mean() < 0.04
    # Against the brightest source pixel within 2 px (the default), on this high-contrast texture
    # only the blob's brighter part stands out (measured 62 % of the core).
    mask, _ = multiview_highlight(shiny, depth, K, ref.R, ref.t, sources, min_excess=0.06, dilate=0)
    assert 0.5 < mask[core].mean() < 0.8 and mask[blob < 0.02].mean() < 0.005
    # Without the blob there is nothing to find.
    mask, _ = multiview_highlight(ref.image, depth, K, ref.R, ref.t, sources, min_excess=0.06)
    assert mask.mean() < 0.01


# -- the estimator's rules -------------------------------------------------------------------


def _kernel_inputs():
    """The plane scene with three sources, its full-resolution level and kernel parameters."""
    problem, depth, normal = plane_scene(num_sources=3)
    options = PatchMatchOptions()
    level = _Level.build(problem, 1.0, use_depth=False, images=_matching_images(problem, options))
    return problem, depth, normal, level, _kernel_params(problem, options)


def test_a_dropped_centre_leaves_the_anchors_windows_alone():
    problem, depth, normal, level, params = _kernel_inputs()
    h, w = depth.shape
    rng = np.random.default_rng(1)
    anchors = rng.integers(0, h * w, (h, w, 8)).astype(np.int32)
    depth = (depth * rng.uniform(0.9, 1.1, depth.shape)).astype(np.float32)
    pixels = np.array([[20, 30], [21, 30], [30, 40]], np.int32)
    dropped = np.zeros((h, w), np.uint8)
    dropped[20, 30] = 1
    plain = _patchmatch.patch_costs(level.views, depth, normal, params, pixels, anchors)
    got = _patchmatch.patch_costs(
        level.views, depth, normal, params, pixels, anchors, None, dropped
    )
    anchors_only = _patchmatch.patch_costs(
        level.views, depth, normal, params.replace(deform_lambda=0.0), pixels, anchors
    )
    np.testing.assert_array_equal(
        got[0], anchors_only[0]
    )  # the dropped pixel: eq. 3 without its centre term
    np.testing.assert_array_equal(got[1:], plain[1:])  # the others unchanged
    assert not np.array_equal(got[0], plain[0])


def test_sources_whose_highlight_the_point_lands_in_are_invisible():
    problem, depth, normal, level, params = _kernel_inputs()
    h, w = depth.shape
    S = len(problem.sources)
    state = _patchmatch.PlaneState(
        depth.copy(),
        normal.copy(),
        np.zeros((h, w), np.float32),
        np.zeros((h, w, S), np.float32),
        np.zeros((h, w, S), np.float32),
        np.full((h, w), 0b111, np.uint32),
    )
    highlight = np.zeros((S, h, w), np.uint8)
    highlight[1, :, : w // 2] = 1  # the left half of source 1
    visible = np.zeros((h, w), np.uint32)
    _patchmatch.visible_sources(
        level.views.without_depths(), state, params, visible, 2.0, 2, None, 0, highlight
    )
    in_highlight = (visible & 0b010) == 0
    assert 0.2 < in_highlight.mean() < 0.8  # part of the reference lands there
    assert ((visible & 0b101) == 0b101).all()  # the other sources stay visible
    # The pixels that lost source 1 are those whose point lands in its left half.
    rows, cols = np.mgrid[0:h, 0:w]
    X = (
        np.stack([cols, rows, np.ones((h, w))], -1).reshape(-1, 3) @ np.linalg.inv(K).T
    ) * depth.reshape(-1, 1)
    s = problem.sources[1]
    uv = (X @ s.R.T + s.t) @ K.T
    u = np.floor(uv[:, 0] / uv[:, 2] + 0.5).reshape(h, w)
    lands = (u >= 0) & (u < w // 2)
    assert (in_highlight == lands).mean() > 0.995
    # Without selection or restoration (all_sources): every source but the highlighted ones.
    _patchmatch.visible_sources(
        level.views.without_depths(),
        _patchmatch.PlaneState(*list(state)[:5], np.zeros((h, w), np.uint32)),
        params,
        visible,
        2.0,
        2,
        None,
        0,
        highlight,
        True,
    )
    assert ((visible & 0b101) == 0b101).all() and np.array_equal(
        (visible & 0b010) == 0, in_highlight
    )


def _shiny_problem(corrected=True, masked=True):
    """The plane scene with a highlight on the reference: a bright saturated patch, with its
    correction (the diffuse image) and its mask given or not."""
    problem, depth, normal = plane_scene(num_sources=3)
    ref = problem.reference
    h, w = depth.shape
    mask = np.zeros((h, w), bool)
    mask[15:40, 25:55] = True
    shiny = np.where(mask, 1.0, ref.image).astype(np.float32)  # saturated: no texture left
    reference = ViewData(
        ref.name,
        shiny,
        ref.K,
        ref.R,
        ref.t,
        corrected=ref.image if corrected else None,
        highlight=mask if masked else None,
    )
    return Problem(reference, problem.sources, problem.depth_range), depth, mask


def test_strong_pixels_in_the_reference_highlight_are_left_to_other_views():
    problem, truth, mask = _shiny_problem()
    options = PatchMatchOptions(num_threads=2, filter_min_region=0)
    skipped = estimate(problem, options)
    # The same corrected image without the mask: the highlight's rules do not apply.
    kept = estimate(_shiny_problem(masked=False)[0], options)
    good = np.abs(kept.depth - truth) <= 0.01 * truth
    # With the corrected image matched, the highlight is reconstructed when kept ...
    assert good[mask].mean() > 0.8, good[mask].mean()
    # ... and mostly left out when its strong pixels are skipped (measured: 10 % kept, the weak
    # pixels); nothing changes far from it.
    assert (skipped.depth[mask] > 0).mean() < 0.25 * (kept.depth[mask] > 0).mean()
    far = ~cv2.dilate(mask.astype(np.uint8), np.ones((25, 25), np.uint8)).astype(bool)
    agree = np.abs(skipped.depth - kept.depth) <= 0.01 * truth
    assert agree[far].mean() > 0.97


def test_corrected_images_are_matched_instead_of_the_originals():
    # Without the mask, so that the highlight's pixels are kept in both.
    options = PatchMatchOptions(num_threads=2, filter_min_region=0)
    problem, truth, mask = _shiny_problem(masked=False)
    with_correction = estimate(problem, options)
    without = estimate(_shiny_problem(corrected=False, masked=False)[0], options)
    good = lambda r: (np.abs(r.depth - truth) <= 0.01 * truth)[mask].mean()  # noqa: E731
    assert good(with_correction) > 0.98, good(with_correction)
    # The corrected patch matches its sources (median cost 0.006); the saturated original does
    # not (0.27), though the planar prior and propagation still give this single plane's depth
    # there (99 % within 1 %).
    cost = lambda r: float(np.median(r.cost[mask]))  # noqa: E731
    assert cost(with_correction) < 0.05 and cost(without) > 0.15, (
        cost(with_correction),
        cost(without),
    )


def test_a_highlight_mask_needs_the_image_size():
    problem, _, _ = plane_scene()
    ref = problem.reference
    with pytest.raises(ValueError, match="highlight mask"):
        ViewData(ref.name, ref.image, ref.K, ref.R, ref.t, highlight=np.zeros((3, 3), bool))
    with pytest.raises(ValueError, match="corrected image"):
        ViewData(ref.name, ref.image, ref.K, ref.R, ref.t, corrected=np.zeros((3, 3), np.float32))


# -- the stage in the dense pipeline, and its ground truth --------------------------------------


@pytest.fixture(scope="module")
def facade(tmp_path_factory):
    from dvpmvs.evaluation.synthetic import SynthOptions, generate

    root = tmp_path_factory.mktemp("highlight") / "facade"
    generate(root, SynthOptions(scene="facade", views=4, width=200, priors=False))
    return root


def test_synthetic_ground_truth_of_highlights(facade):
    from dvpmvs.evaluation.synthetic import HIGHLIGHT_MIN_SHARE, HIGHLIGHT_MIN_SPECULAR
    from dvpmvs.maps import read_extra_map

    gt = facade / "ground_truth"
    found = 0
    for name in ("0000.png", "0001.png", "0002.png", "0003.png"):
        image = cv2.imread(str(facade / "images" / name))[..., ::-1] / 255.0
        diffuse = cv2.imread(str(gt / "diffuse" / name))[..., ::-1] / 255.0
        specular = read_extra_map(gt / "specular" / f"{name}.bin")
        mask = cv2.imread(str(gt / "highlights" / name), cv2.IMREAD_GRAYSCALE) > 127
        found += mask.sum()
        # The image is the diffuse image plus the specular term, where nothing saturates.
        unclipped = (image.max(axis=2) < 0.97) & (specular > 0)
        error = np.abs(image - diffuse - specular[..., None])[unclipped]
        assert error.mean() < 2 / 255, error.mean()
        # The mask is the stated rule (against the noisy image: a grey level's slack).
        share = specular / np.maximum(image.mean(axis=2), 1e-6)
        sure = (specular >= HIGHLIGHT_MIN_SPECULAR + 0.01) & (share >= HIGHLIGHT_MIN_SHARE * 1.1)
        assert mask[sure].all() and not mask[specular < HIGHLIGHT_MIN_SPECULAR].any()
    assert found > 500  # the facade's glossy windows


@pytest.mark.slow
def test_dense_with_highlights_stores_reuses_and_scores(facade, tmp_path):
    from dvpmvs.dense import DenseOptions, run_dense
    from dvpmvs.evaluation.depth_metrics import evaluate_depth_maps, pooled_highlight_shares
    from dvpmvs.evaluation.highlight_metrics import evaluate_highlight_masks, pooled_mask_metrics
    from dvpmvs.workspace import Workspace

    priors = {
        "depth_prior": {"name": "coarse_mvs"},
        "normal_prior": {"name": "from_depth"},
        "edge": {"name": "roberts"},
        "highlight": {"name": "dichromatic"},
    }
    options = DenseOptions(priors=priors, fuse=False, patch_match=PatchMatchOptions(num_threads=2))
    out = tmp_path / "run"
    summary = run_dense(Workspace.open(facade), options, progress=False, out=out)
    stereo = out / "stereo"
    names = [f"{i:04d}.png" for i in range(4)]
    for name in names:
        for kind in ("corrected", "mask", "geometric.corrected", "geometric.mask"):
            assert (stereo / "highlights" / f"{name}.{kind}.bin").is_file(), (name, kind)
        assert (
            json.loads((stereo / "provenance" / f"{name}.highlight.json").read_text())["state"]
            == "complete"
        )
    assert sorted(summary.highlight_seconds) == names
    # The geometric pass's masks join the provider's with the multi-view evidence.
    from dvpmvs.maps import read_extra_map

    for name in names:
        single_mask = read_extra_map(stereo / "highlights" / f"{name}.mask.bin") > 0.5
        final_mask = read_extra_map(stereo / "highlights" / f"{name}.geometric.mask.bin") > 0.5
        assert final_mask[single_mask].all()
    truth = facade / "ground_truth" / "highlights"
    single = pooled_mask_metrics(evaluate_highlight_masks(stereo / "highlights", truth, "single"))
    final = pooled_mask_metrics(evaluate_highlight_masks(stereo / "highlights", truth, "final"))
    assert final.true_positive >= single.true_positive > 0
    shares = pooled_highlight_shares(
        evaluate_depth_maps(stereo / "depth_maps", facade / "ground_truth" / "depth_maps")
    )
    assert shares["highlight_pixels"] > 500 and 0 <= shares["highlight_within_1_percent"] <= 1
    # A rerun reuses everything; another provider setting recomputes the outputs and the maps.
    again = run_dense(Workspace.open(facade), options, progress=False, out=out)
    assert again.highlight_seconds == {} and all(r.action == "reused" for r in again.reports)
    changed = {**priors, "highlight": {"name": "dichromatic", "min_specular": 0.1}}
    other = run_dense(
        Workspace.open(facade),
        DenseOptions(
            priors=changed,
            fuse=False,
            geometric=False,
            patch_match=PatchMatchOptions(num_threads=2),
        ),
        progress=False,
        out=out,
    )
    assert sorted(other.highlight_seconds) == names and all(
        r.action == "computed" for r in other.reports
    )


def test_masks_of_a_reduced_run_are_scored_against_the_ground_truth_at_their_size(tmp_path):
    import cv2

    from dvpmvs.errors import DvpmvsError
    from dvpmvs.evaluation.highlight_metrics import evaluate_highlight_masks, truth_at_size
    from dvpmvs.maps import write_extra_map

    truth = np.zeros((240, 320), np.uint8)
    truth[40:120, 80:201] = (
        255  # 121 columns: the reduced column 100 is half highlight, which is not most
    )
    reduced = np.zeros((120, 160), bool)
    reduced[20:60, 40:100] = True
    assert np.array_equal(truth_at_size(truth > 127, (120, 160)), reduced)
    assert np.array_equal(truth_at_size(truth > 127, (240, 320)), truth > 127)
    assert (
        truth_at_size(truth > 127, (61, 80)).sum() == 20 * 30
    )  # a rounded size keeps the aspect ratio
    with pytest.raises(DvpmvsError, match="another aspect ratio"):
        truth_at_size(truth > 127, (120, 120), "0000.png")
    # A run's masks at half the images' size against the full-size truth folder.
    (tmp_path / "truth").mkdir()
    cv2.imwrite(str(tmp_path / "truth" / "0000.png"), truth)
    found = reduced.copy()
    found[20:60, 90:100] = False  # 400 of the 2,400 missed
    write_extra_map(tmp_path / "0000.png.mask.bin", found.astype(np.float32))
    (m,) = evaluate_highlight_masks(tmp_path, tmp_path / "truth", "single")
    assert (m.true_positive, m.false_positive, m.false_negative) == (2000, 0, 400)


def test_highlight_masks_and_depth_scored_inside_and_outside():
    from dvpmvs.evaluation.depth_metrics import depth_map_metrics
    from dvpmvs.evaluation.highlight_metrics import mask_metrics

    truth_mask = np.zeros((10, 10), bool)
    truth_mask[2:6, 2:6] = True  # 16 pixels
    found = np.zeros((10, 10), bool)
    found[2:6, 2:4] = True  # 8 of them
    found[8, :] = True  # and 10 others
    m = mask_metrics("v", found, truth_mask)
    assert (m.true_positive, m.false_positive, m.false_negative) == (8, 10, 8)
    assert m.precision == pytest.approx(8 / 18) and m.recall == pytest.approx(0.5)
    truth = np.full((10, 10), 2.0, np.float32)
    depth = truth.copy()
    depth[2:6, 2:6] = 2.5  # wrong inside the highlight
    depth[0, :] = 0  # missing outside
    metrics = depth_map_metrics("v", depth, truth, highlight=truth_mask)
    assert metrics.highlight_pixels == 16 and metrics.highlight_within_1_percent == 0.0
    assert metrics.highlight_estimated == 1.0
    assert metrics.outside_within_1_percent == pytest.approx(74 / 84)
