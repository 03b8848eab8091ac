"""A stored product of the dense stage, one node of its graph: a view's mask, its single-view
highlight outputs, their multi-view refinement, its region labels, or its maps of a pass. A
product knows what it is made from (its inputs and their fingerprint), the files it writes, the
record on disk that says how those files stand (:class:`~dvpmvs.provenance.CachedOutput`, the
record scheme every stored product of dvpmvs shares) and the products whose files it reads; the
plan (:mod:`dvpmvs.dense.plan`) builds them once, the tasks (:mod:`dvpmvs.dense.tasks`) make
them."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dvpmvs.passes import Pass
from dvpmvs.provenance import CachedOutput, Record, Status
from dvpmvs.view import View

__all__ = ["MASK", "HIGHLIGHTS", "REFINED_HIGHLIGHTS", "REGIONS", "Product", "product_key"]

MASK = "mask"  # the mask provider's keep mask of a view
HIGHLIGHTS = "highlights"  # the highlight provider's outputs of a view
REFINED_HIGHLIGHTS = "highlights-geometric"  # refined from the photometric maps (multi-view)
REGIONS = "regions"  # the aligned prior's region labels of a view (priors, then segmentation)
# A view's maps of a pass are the product of kind ``pass_.value``.


def product_key(kind: str, name: str) -> str:
    """The key of a view's product of ``kind``: its task's key in the run's graph."""
    return f"{kind}:{name}"


@dataclass
class Product:
    """``kind`` of ``view``: ``stored`` holds its inputs, fingerprint, files and the record found
    on disk; ``files``: what it writes (kind -> path); ``after``: the keys of the products whose
    files it reads (:func:`product_key`)."""

    kind: str
    view: View
    stored: CachedOutput
    files: dict[str, Path]
    after: tuple[str, ...] = ()

    @property
    def key(self) -> str:
        return product_key(self.kind, self.view.name)

    @property
    def pass_(self) -> Pass:
        """The pass whose maps this product is (a view pass's product only)."""
        return Pass(self.kind)

    @property
    def inputs(self) -> dict:
        return self.stored.inputs

    @property
    def fingerprint(self) -> str:
        return self.stored.fingerprint

    @property
    def record(self) -> Record | None:
        """The record found on disk when the plan was made (None: none)."""
        return self.stored.previous

    @property
    def status(self) -> Status:
        return self.stored.state

    def wanted(self, overwrite: bool) -> bool:
        """Whether a run makes it: its files are not current, or the user asked for all."""
        return overwrite or not self.status.reusable
