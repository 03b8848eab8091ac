"""Non-learned plugins of dvpmvs, registered through entry points (see pyproject.toml)."""
