"""The harness's Hydra config: the ``evaluate`` group that ``dvpmvs dense`` and ``dvpmvs bench``
take where the harness is installed (added to the search path by entry point, as the plugins'
config groups; ``dense.yaml`` names it optional, so the core composes without it)."""
