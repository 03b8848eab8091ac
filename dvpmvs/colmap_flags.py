"""COLMAP's command-line spellings of the dense stage's options, read as dvpmvs's.

A COLMAP user types ``--workspace_path W --PatchMatchStereo.max_image_size 1600`` (as
``colmap patch_match_stereo`` and ``colmap stereo_fusion`` take them). ``dvpmvs dense`` and
``dvpmvs fuse`` take those flags where an option of ours means the same thing (an alias, its
value converted where the units differ), ignore with a note the ones that only tune COLMAP's GPU
or its cache, and stop with one line naming our nearest option for the ones whose meaning
differs: a silent translation there would run something else than the user asked for.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["ColmapFlagError", "translate_colmap_flags"]


class ColmapFlagError(ValueError):
    """A COLMAP flag dvpmvs does not take, with what to write instead."""


@dataclass(frozen=True)
class _Alias:
    key: str  # our option
    convert: Callable[[str, str], str] | None = None  # (flag, value) -> our value


@dataclass(frozen=True)
class _Note:
    text: str  # why the flag changes nothing here: printed, the run goes on


@dataclass(frozen=True)
class _Refused:
    text: str  # what to write instead


def _boolean(flag: str, value: str) -> str:
    lowered = value.strip().lower()
    if lowered in ("1", "true", "yes", "on"):
        return "true"
    if lowered in ("0", "false", "no", "off"):
        return "false"
    raise ColmapFlagError(f"{flag} takes 1 or 0 (true or false), got {value!r}")


def _number(flag: str, value: str) -> float:
    try:
        return float(value)
    except ValueError:
        raise ColmapFlagError(f"{flag} takes a number, got {value!r}") from None


def _min_ncc(flag: str, value: str) -> str:
    # Our matching cost is 1 - NCC (bilateral-weighted), so a minimum NCC is a maximum cost.
    return repr(1.0 - _number(flag, value))


def _min_num_pixels(flag: str, value: str) -> str:
    # COLMAP counts the reference pixel among the agreeing ones; min_consistent_views does not.
    pixels = _number(flag, value)
    if pixels != int(pixels) or pixels < 2:
        raise ColmapFlagError(
            f"{flag} takes a whole number of at least 2 here (the reference pixel and one other "
            f"view: fusion_options.min_consistent_views=1), got {value!r}"
        )
    return str(int(pixels) - 1)


def _quoted(value: str) -> str:
    """``value`` as Hydra's override grammar reads it back as this string."""
    if value and all(c.isascii() and (c.isalnum() or c in "/._-~+:@") for c in value):
        return value
    escaped = value.replace("\\", "\\\\").replace("'", "\\'")
    return f"'{escaped}'"


_NO_GPU = _Note("dvpmvs runs on the CPU (num_threads= sets its threads)")
_CACHE = _Note("dvpmvs holds fusion_options.cache_views views' maps in memory (a number of views)")

# The flags of `colmap patch_match_stereo` and `colmap stereo_fusion` (COLMAP 3.9-3.12), by
# the subcommands that take them.
_COMMON = {
    "workspace_path": _Alias("workspace"),
    "workspace_format": _Refused(
        "dvpmvs reads COLMAP workspaces only: write --workspace_format COLMAP or leave it out"
    ),
    "pmvs_option_name": _Refused("dvpmvs reads COLMAP workspaces only (no PMVS option files)"),
    "random_seed": _Alias("seed"),
    "log_to_stderr": _Note("dvpmvs prints to the terminal; verbose=true prints more"),
    "log_level": _Note("dvpmvs prints to the terminal; verbose=true prints more, quiet=true less"),
    "project_path": _Refused(
        "dvpmvs reads no COLMAP .ini project: give its options on the command line "
        "(key=value, or COLMAP's --flag value)"
    ),
}
_PATCH_MATCH = {
    "PatchMatchStereo.max_image_size": _Alias("max_image_size"),
    "PatchMatchStereo.gpu_index": _NO_GPU,
    "PatchMatchStereo.depth_min": _Refused(
        "give both bounds as depth_range=[MIN,MAX] (for every view, as COLMAP's pair)"
    ),
    "PatchMatchStereo.depth_max": _Refused(
        "give both bounds as depth_range=[MIN,MAX] (for every view, as COLMAP's pair)"
    ),
    "PatchMatchStereo.window_radius": _Alias("patch_match.window_radius"),
    "PatchMatchStereo.window_step": _Alias("patch_match.window_step"),
    "PatchMatchStereo.sigma_spatial": _Alias("patch_match.sigma_spatial"),
    "PatchMatchStereo.sigma_color": _Alias("patch_match.sigma_color"),
    "PatchMatchStereo.num_samples": _Refused(
        "dvpmvs chooses each pixel's source views by ACMMP's checkerboard voting, without "
        "Monte-Carlo samples; the number of sources is patch_match.max_sources"
    ),
    "PatchMatchStereo.ncc_sigma": _Refused(
        "dvpmvs weighs its source views by ACMMP's rule (no NCC sigma); see "
        "patch_match.max_sources and patch_match.strong_max_cost"
    ),
    "PatchMatchStereo.min_triangulation_angle": _Alias("view_selector.min_triangulation_angle"),
    "PatchMatchStereo.incident_angle_sigma": _Refused(
        "dvpmvs has no incident-angle weight; source views are chosen per pixel by cost"
    ),
    "PatchMatchStereo.num_iterations": _Refused(
        "patch_match.num_iterations counts the red-black sweeps at each of the pyramid's "
        "patch_match.num_scales levels (default 1, COLMAP's 5 sweeps at one level): write "
        "patch_match.num_iterations=N knowing that"
    ),
    "PatchMatchStereo.geom_consistency": _Alias("geometric", _boolean),
    "PatchMatchStereo.geom_consistency_regularizer": _Alias("patch_match.geom_weight"),
    "PatchMatchStereo.geom_consistency_max_cost": _Alias("patch_match.geom_max_error"),
    "PatchMatchStereo.filter": _Refused(
        "dvpmvs always filters its maps (patch_match.filter_max_cost, "
        "patch_match.filter_min_region); leave --PatchMatchStereo.filter out"
    ),
    "PatchMatchStereo.filter_min_ncc": _Alias("patch_match.filter_max_cost", _min_ncc),
    "PatchMatchStereo.filter_min_triangulation_angle": _Refused(
        "dvpmvs filters no pixel by its triangulation angle; fusion checks the views' agreement "
        "(fusion_options.*)"
    ),
    "PatchMatchStereo.filter_min_num_consistent": _Refused(
        "dvpmvs checks consistency in fusion: fusion_options.min_consistent_views (other views "
        "that must agree with a pixel)"
    ),
    "PatchMatchStereo.filter_geom_consistency_max_cost": _Refused(
        "fusion's agreement bound is fusion_options.max_reproj_error (pixels)"
    ),
    "PatchMatchStereo.cache_size": _CACHE,
    "PatchMatchStereo.allow_missing_files": _Alias("fusion_options.allow_missing", _boolean),
    "PatchMatchStereo.write_consistency_graph": _Refused(
        "dvpmvs writes no consistency graphs (fusion reads the maps themselves)"
    ),
    "PatchMatchStereo.config_path": _Refused(
        "dvpmvs reads WS/stereo/patch-match.cfg (view_selector=colmap_cfg)"
    ),
    "config_path": _Refused("dvpmvs reads WS/stereo/patch-match.cfg (view_selector=colmap_cfg)"),
}
_FUSION = {
    "input_type": _Alias("input_type"),
    "output_type": _Refused("dvpmvs writes the fused cloud as PLY (COLMAP's --output_type PLY)"),
    "output_path": _Alias("output"),
    "bbox_path": _Refused("dvpmvs has no bounding box for fusion; masks (mask=files) cut views"),
    "StereoFusion.mask_path": _Alias("mask.path"),
    "StereoFusion.num_threads": _Alias("num_threads"),
    "StereoFusion.max_image_size": _Refused(
        "fusion reads the maps at their size; max_image_size= sets the size they are computed at"
    ),
    "StereoFusion.min_num_pixels": _Alias("fusion_options.min_consistent_views", _min_num_pixels),
    "StereoFusion.max_num_pixels": _Refused(
        "dvpmvs fuses every agreeing pixel (no cap); fusion_options.max_neighbours bounds the "
        "views checked"
    ),
    "StereoFusion.max_traversal_depth": _Refused(
        "dvpmvs fuses a pixel with the views that see it directly (no graph traversal); "
        "fusion_options.max_neighbours bounds them"
    ),
    "StereoFusion.max_reproj_error": _Alias("fusion_options.max_reproj_error"),
    "StereoFusion.max_depth_error": _Alias("fusion_options.max_depth_error"),
    "StereoFusion.max_normal_error": _Alias("fusion_options.max_normal_error"),
    "StereoFusion.check_num_images": _Alias("fusion_options.max_neighbours"),
    "StereoFusion.cache_size": _CACHE,
    "StereoFusion.use_cache": _CACHE,
}
# dense computes the maps and fuses them (both of COLMAP's programs); fuse is stereo_fusion.
# dense fuses the maps of its last pass (geometric=), so --input_type has no place there.
_FLAGS = {
    "dense": {**_COMMON, **_PATCH_MATCH, **{k: v for k, v in _FUSION.items() if k != "input_type"}},
    "fuse": {**_COMMON, **_FUSION},
}


def translate_colmap_flags(command: str, argv: list[str]) -> tuple[list[str], list[str]]:
    """``argv`` with COLMAP's flags (``--flag value`` or ``--flag=value``) replaced by our
    overrides, and the notes to print for the flags that change nothing here. Raises
    ColmapFlagError for a COLMAP flag we do not take, saying what to write instead. Other
    arguments (ours, Hydra's flags) are kept in place."""
    flags = _FLAGS.get(command)
    if flags is None:
        return argv, []
    out: list[str] = []
    notes: list[str] = []
    mask_given = any(arg.startswith("mask=") for arg in argv)
    index = 0
    while index < len(argv):
        arg = argv[index]
        name, sep, value = arg[2:].partition("=") if arg.startswith("--") else ("", "", "")
        meaning = flags.get(name)
        if meaning is None and name.startswith(("PatchMatchStereo.", "StereoFusion.")):
            raise ColmapFlagError(_unknown(name, flags))
        if meaning is None:
            out.append(arg)
            index += 1
            continue
        flag = f"--{name}"
        if not sep:
            if index + 1 >= len(argv):
                raise ColmapFlagError(f"{flag} needs a value ({flag} VALUE, as COLMAP takes it)")
            value = argv[index + 1]
            index += 1
        index += 1
        if isinstance(meaning, _Note):
            notes.append(f"{flag} {value}: ignored, {meaning.text}")
        elif isinstance(meaning, _Refused):
            if name == "workspace_format" and value.strip().upper() == "COLMAP":
                continue
            raise ColmapFlagError(f"{flag} is not taken: {meaning.text}")
        else:
            converted = meaning.convert(flag, value) if meaning.convert else _quoted(value)
            key = meaning.key
            if key == "fusion_options.max_reproj_error" and "fusion=colmap" in argv:
                key = "fusion_options.colmap_max_reproj_error"  # what COLMAP's fusion is handed
            out.append(f"{key}={converted}")
            if meaning.key == "mask.path" and not mask_given:
                out += ["mask=files", "mask.layout=colmap"]
                mask_given = True
    return out, notes


def _unknown(name: str, flags: dict) -> str:
    from difflib import get_close_matches

    nearest = get_close_matches(name, list(flags), n=1, cutoff=0.6)
    hint = f"; did you mean --{nearest[0]}?" if nearest else ""
    return f"--{name} is no option of COLMAP's that dvpmvs knows{hint}"
