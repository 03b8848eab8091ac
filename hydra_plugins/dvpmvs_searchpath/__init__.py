"""Hydra search-path plugin of dvpmvs (Hydra discovers it in the ``hydra_plugins`` namespace)."""
