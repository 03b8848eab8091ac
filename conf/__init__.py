"""Hydra configuration tree of the ``dvpmvs`` command (installed as ``dvpmvs.conf``)."""
