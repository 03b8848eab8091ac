"""Hydra configuration tree of the ``dvpmvs`` command (installed as ``dvpmvs.conf``).

The option groups whose defaults live in their dataclasses (``patch_match``, ``segmentation``,
``fusion_options``, ``workspace``, ``meshing_options``, ``sfm_options``) are stored in Hydra's
ConfigStore when this package is imported, which Hydra does when it reads it: so composing with
Hydra's own API (``initialize_config_module("dvpmvs.conf")``) finds them too."""

from dvpmvs.config import register_option_configs

register_option_configs()
