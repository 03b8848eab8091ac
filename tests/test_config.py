"""The configuration a command runs with (``dvpmvs.config``): Hydra's composition of the configs,
the presets and the paper's ablations as overrides, and the options objects built from it."""

import pytest

from dvpmvs.config import (
    ConfigError,
    compose,
    dense_options,
    number_list,
    number_pair,
    typed,
    workspace_options,
)


def _compose(*overrides):
    return dense_options(compose("dense", ["workspace=unused", *overrides]))


def _switches(options):
    """The component switches of paper sections 3.2-3.5 as they stand in ``options``."""
    pm, seg = options.patch_match, options.segmentation
    return {
        "deformable": pm.deformable,
        "agn": seg is not None,
        "coplanar": pm.anchor_coplanar,
        "mon": seg is not None and seg.use_normals,
        "ero": seg is not None and seg.erosion and seg.dilation,
        "fil": seg is not None and seg.filtering,
        "max": pm.area_maximisation,
        "vis": pm.anchor_visibility,
        "res": pm.visibility_restoration,
        "nor": pm.normal_aggregation,
        "dep": pm.depth_aggregation,
        "hig": options.priors["highlight"]["name"] != "none" and pm.highlight_multiview,
    }


# Each Table IV row is the paper's full method with exactly its component(s) off.
@pytest.mark.parametrize(
    "method, off",
    [
        ("w_o_agn", {"agn": False, "mon": False, "ero": False, "fil": False, "coplanar": True}),
        ("w_o_mon", {"mon": False}),
        ("w_o_ero", {"ero": False}),
        ("w_o_fil", {"fil": False}),
        ("w_o_har", {"max": False, "vis": False}),
        ("w_o_max", {"max": False}),
        ("w_o_res", {"res": False}),
        ("w_o_vis", {"vis": False}),
        ("w_o_geo", {"nor": False, "dep": False, "hig": False}),
        ("w_o_nor", {"nor": False}),
        ("w_o_dep", {"dep": False}),
        ("w_o_hig", {"hig": False}),
    ],
)
def test_table_iv_rows_are_the_paper_method_without_one_component(method, off):
    paper = _switches(_compose("method=paper"))
    assert all(value for key, value in paper.items() if key != "coplanar") and not paper["coplanar"]
    assert _switches(_compose(f"method={method}")) == {**paper, **off}


def test_the_paper_method_uses_table_v_parameters_and_the_default_keeps_only_anchor_visibility_of_3_4_and_3_5():
    paper = _compose("method=paper")
    seg, pm = paper.segmentation, paper.patch_match
    assert (
        seg.min_region,
        seg.plane_similarity,
        seg.normal_similarity,
        seg.erosion_gain,
        seg.min_inlier_ratio,
        seg.filter_distance,
    ) == (500, 0.5, 0.4, 1.2, 0.7, 0.8)
    assert (pm.deform_centre_step, pm.deform_anchor_step) == (5, 2)  # eq. 3's B_p and B_s
    default = _switches(_compose())
    assert default == _switches(_compose("method=default"))
    assert default["deformable"] and default["agn"] and default["mon"]
    assert (
        default["vis"] and default["res"]
    )  # visibility-aware deformation, with the detail restorer
    assert not (default["max"] or default["nor"] or default["dep"] or default["hig"])
    assert _compose("method=paper").priors["highlight"]["name"] == "multiview"
    assert not _switches(_compose("method=baseline"))["deformable"]
    # Presets combine with the priors' groups, and a key on the command line wins over them.
    options = _compose(
        "method=w_o_ero",
        "depth_prior=file",
        "depth_prior.path=priors",
        "patch_match.area_maximisation=false",
    )
    assert options.priors["depth_prior"] == {
        "name": "file",
        "path": "priors",
        "metric": False,
        "kind": "depth",
        "resize": False,
    }
    assert not options.patch_match.area_maximisation and options.patch_match.anchor_visibility
    # Table V's symbols stand for the options they name (the paper's own sweep: segmentation.eta=...).
    swept = _compose("method=paper", "segmentation.eta=100", "segmentation.kappa=0.6")
    assert (swept.segmentation.min_region, swept.segmentation.min_inlier_ratio) == (100, 0.6)
    assert _compose("method=paper").segmentation.min_region == 500


@pytest.mark.parametrize(
    "quality, expected",
    [
        (
            "high",
            dict(
                prior_iterations=2, geom_deformable=True, deform_centre_step=5, deform_anchor_step=2
            ),
        ),
        (
            "medium",
            dict(
                prior_iterations=1, geom_deformable=True, deform_centre_step=5, deform_anchor_step=2
            ),
        ),
        (
            "low",
            dict(
                prior_iterations=1,
                geom_deformable=False,
                deform_centre_step=2,
                deform_anchor_step=5,
            ),
        ),
        (
            "fast",
            dict(
                prior_iterations=1,
                geom_deformable=True,
                deform_centre_step=5,
                deform_anchor_step=2,
                max_sources=5,
            ),
        ),
    ],
)
def test_quality_presets_are_config_overrides(quality, expected):
    from dvpmvs.options.patch_match import PatchMatchOptions

    cfg = compose("dense", ["workspace=unused", f"quality={quality}", "method=w_o_ero"])
    default = dense_options(compose("dense", ["workspace=unused"]))
    # A key given on the command line wins over the preset.
    explicit = dense_options(
        compose(
            "dense", ["workspace=unused", f"quality={quality}", "patch_match.prior_iterations=3"]
        )
    )
    options = dense_options(cfg)
    assert {key: getattr(options.patch_match, key) for key in expected} == expected
    assert not options.segmentation.erosion  # the presets combine with the methods
    assert explicit.patch_match.prior_iterations == 3
    # `high` is the default, the same as the estimator's own defaults.
    for key in expected:
        assert getattr(default.patch_match, key) == getattr(PatchMatchOptions(), key)
    assert default.patch_match.prior_iterations == 2


def test_the_fast_preset_reads_the_workspace_its_way_in_every_command():
    # Its five sources by an angle score and its half size, wherever it is given (the demo
    # read the workspace with the defaults: full size, COLMAP's rule).
    for command in ("dense", "bench", "reconstruct", "demo"):
        cfg = compose(command, ["workspace=unused", "quality=fast"])
        assert cfg.view_selector.name == "sparse_score", command
        assert workspace_options(cfg).resolution_level == 1, command
        assert compose(command, ["workspace=unused"]).view_selector.name == "colmap_cfg"
    given = compose("dense", ["workspace=unused", "quality=fast", "view_selector=colmap_cfg"])
    assert given.view_selector.name == "colmap_cfg"  # the command line wins


def test_overrides_are_a_list_of_strings_and_a_bad_key_names_the_command():
    with pytest.raises(TypeError, match="overrides must be a list of 'key=value' strings"):
        compose("dense", "quality=fast")
    with pytest.raises(ConfigError, match="dvpmvs dense workspace=x patch_mach.x=1: "):
        compose("dense", ["workspace=x", "patch_mach.x=1"])


def test_workspace_keys_are_checked_with_the_form_they_take():
    options = workspace_options(
        compose("dense", ["workspace=x", "depth_range=[0.5,20]", "max_image_size=640"])
    )
    assert options.depth_range == (0.5, 20.0) and options.max_image_size == 640
    with pytest.raises(
        ConfigError, match=r"depth_range must be two numbers, depth_range=\[min,max\]"
    ):
        workspace_options(compose("dense", ["workspace=x", "depth_range=[1]"]))
    with pytest.raises(ConfigError, match="invalid workspace option: depth_margin"):
        workspace_options(compose("dense", ["workspace=x", "depth_margin=-1"]))


def test_numbers_are_not_converted_silently():
    assert number_pair([1, 2.5], "k", "[a,b]") == (1.0, 2.5)
    assert number_list(0.02, "tolerances", "[0.02,0.1]") == [0.02]
    with pytest.raises(ConfigError, match="tolerances must be positive numbers"):
        number_list([0.02, -1], "tolerances", "[0.02,0.1]")
    cfg = compose("dense", ["workspace=x", "+flag=maybe"])
    with pytest.raises(ConfigError, match="flag must be true or false, got 'maybe'"):
        typed(cfg, "flag", bool)
