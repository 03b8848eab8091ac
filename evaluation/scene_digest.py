"""The identity of a rendered scene: the digest of its content, part by part.

A scene is what its files hold, not the version of the code that rendered it: two machines that
render the same parameters have the same scene only if they wrote the same pixels, the same sparse
model and the same ground truth. :func:`scene_digest` hashes each part of a workspace made by
``dvpmvs synth`` (or ``dvpmvs bench``):

- ``images``: the images' decoded pixels (PNG files compress differently between libpng builds;
  their pixels are the scene);
- ``sparse``: the sparse model and the stereo configuration (``sparse/``, ``stereo/*.cfg``);
- ``ground_truth``: depth and normal maps, scans, masks (pixels for PNG files, bytes otherwise);
- ``priors``: the simulated priors, when rendered;
(the ``previews/`` folders of the last two are left out: pictures drawn from the data, not data);
- ``parameters``: ``scene.json`` (the options and the statistics the generator wrote).

The scene's digest is the SHA-256 of the parts' digests; its first 12 hex digits are what the
documents quote beside each table (``room 8v 800 seed 0: 3f2a...``).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

__all__ = [
    "SceneDigest",
    "scene_digest",
    "scene_key",
    "documented",
    "record",
    "compare_with_documented",
    "vector_extensions",
    "cpu_features",
    "PARTS",
    "SHORT",
    "DOCUMENTED",
]

# part -> the folders (or files) of the workspace it covers
PARTS = {
    "images": ("images",),
    "sparse": ("sparse", "stereo/*.cfg"),  # the stereo folder's maps are a run's, not the scene's
    "ground_truth": ("ground_truth",),
    "priors": ("simulated_priors",),
    "parameters": ("scene.json",),
}
SHORT = 12  # hex digits quoted in the documents
# Previews are pictures drawn from the parts' data (colour maps of depth and normals), not the scene:
# their colours round differently between numpy releases while the data they show does not.
_PREVIEWS = "previews"
# The reference renders: each scene's digest as rendered where the documents' figures are
# measured, with that machine's libraries and the CPU's vector extensions (written by ``record``;
# the documents quote the short digest beside each table that ran on the scene).
DOCUMENTED = Path(__file__).resolve().parent / "scenes" / "digests.json"


@dataclass(frozen=True)
class SceneDigest:
    """A scene's digest and those of its parts (hex SHA-256)."""

    parts: dict[str, str] = field(default_factory=dict)

    @property
    def digest(self) -> str:
        text = json.dumps(self.parts, sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode()).hexdigest()

    @property
    def short(self) -> str:
        return self.digest[:SHORT]

    def differing(self, other: SceneDigest | dict) -> list[str]:
        """The parts whose digests differ from ``other``'s (a SceneDigest or its parts)."""
        theirs = other.parts if isinstance(other, SceneDigest) else dict(other)
        return sorted(
            part
            for part in set(self.parts) | set(theirs)
            if self.parts.get(part) != theirs.get(part)
        )

    def to_json(self) -> dict:
        return {"digest": self.digest, "parts": dict(self.parts)}


def _file_content(path: Path) -> bytes:
    """What a file contributes: a PNG's decoded pixels with their shape and type, else its bytes."""
    if path.suffix.lower() == ".png":
        pixels = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if pixels is None:
            raise ValueError(f"cannot decode {path}: the scene is incomplete; render it again")
        pixels = np.ascontiguousarray(pixels)
        return f"{pixels.shape}{pixels.dtype.str}".encode() + pixels.tobytes()
    return path.read_bytes()


def _part_digest(root: Path, entries: tuple[str, ...]) -> str | None:
    files: list[Path] = []
    for entry in entries:
        path = root / entry
        if "*" in entry:
            files += [p for p in root.glob(entry) if p.is_file()]
        elif path.is_file():
            files.append(path)
        elif path.is_dir():
            files += [
                p
                for p in path.rglob("*")
                if p.is_file()
                and not p.name.startswith(".")
                and _PREVIEWS not in p.relative_to(path).parts
            ]
    if not files:
        return None
    digest = hashlib.sha256()
    for path in sorted(files, key=lambda p: p.relative_to(root).as_posix()):
        content = _file_content(path)
        digest.update(path.relative_to(root).as_posix().encode() + b"\0")
        digest.update(hashlib.sha256(content).digest())
    return digest.hexdigest()


def scene_digest(workspace: str | Path) -> SceneDigest:
    """The digest of the scene rendered into ``workspace``, part by part (parts the scene does
    not have, such as priors not rendered, are left out)."""
    root = Path(workspace)
    parts = {}
    for part, entries in PARTS.items():
        digest = _part_digest(root, entries)
        if digest is not None:
            parts[part] = digest
    if "images" not in parts or "sparse" not in parts:
        raise ValueError(f"{root} holds no rendered scene (images/ and sparse/ are needed)")
    return SceneDigest(parts)


def scene_key(scene: str, views: int, width: int, seed: int) -> str:
    """The name of a rendered scene, as ``dvpmvs bench`` names its folder: ``room_8v_800_seed0``."""
    return f"{scene}_{views}v_{width}_seed{seed}"


def vector_extensions() -> dict[str, list[str]]:
    """The vector paths this process dispatches to: OpenCV's and numpy's (beyond their baselines)."""
    line = cv2.getCPUFeaturesLine().split()
    opencv = [f.strip("*") for f in line if f.startswith("*") and not f.endswith("?")]
    umath = _numpy_umath()
    numpy_paths = [f for f in umath.__cpu_dispatch__ if umath.__cpu_features__.get(f)]
    return {"opencv": opencv, "numpy": numpy_paths}


def _numpy_umath():
    try:
        from numpy._core import _multiarray_umath as umath
    except ImportError:  # numpy < 2
        from numpy.core import _multiarray_umath as umath
    return umath


def cpu_features() -> dict[str, bool]:
    """The CPU's features as numpy reads them (``{"AVX2": True, "FMA3": True, ...}``)."""
    return dict(_numpy_umath().__cpu_features__)


def _documented_all() -> dict:
    try:
        return json.loads(DOCUMENTED.read_text())
    except (OSError, ValueError):
        return {}


def documented(key: str) -> dict | None:
    """The reference render of scene ``key`` (digest, parts, libraries, vector extensions), or None."""
    return _documented_all().get(key)


def record(key: str, digest: SceneDigest) -> None:
    """Record ``digest`` as the reference render of scene ``key``, with this machine's libraries."""
    from dvpmvs.maps import atomic_path
    from dvpmvs.provenance import library_versions

    entries = _documented_all()
    entries[key] = {
        "short": digest.short,
        **digest.to_json(),
        "libraries": library_versions(),
        "vector_extensions": vector_extensions(),
    }
    with atomic_path(DOCUMENTED) as tmp:
        tmp.write_text(json.dumps(dict(sorted(entries.items())), indent=2) + "\n")


def compare_with_documented(key: str, digest: SceneDigest) -> str:
    """One line for the user: the scene's digest and whether it is the one the documents' figures
    were measured on; when not, which parts differ and what differs in the environment."""
    from dvpmvs.provenance import library_versions

    entry = documented(key)
    if entry is None:
        return f"scene {key}: digest {digest.short} (no reference render of this scene is recorded)"
    if entry["digest"] == digest.digest:
        return f"scene {key}: digest {digest.short}, the reference render (figures quoting it are comparable)"
    parts = digest.differing(entry["parts"])
    libraries = library_versions()
    changed = [
        f"{name} {entry['libraries'].get(name)} there, {version} here"
        for name, version in libraries.items()
        if entry["libraries"].get(name) != version
    ]
    ours, theirs = vector_extensions(), entry.get("vector_extensions", {})
    vectors = [
        f"{lib} {'+'.join(theirs.get(lib, [])) or 'baseline'} there, {'+'.join(ours[lib]) or 'baseline'} here"
        for lib in ours
        if ours[lib] != theirs.get(lib)
    ]
    why = (
        "; ".join(changed + vectors)
        or "the same libraries and vector paths (another generator's code?)"
    )
    return (
        f"scene {key}: digest {digest.short} is NOT the reference render's {entry['short']} (differing: "
        f"{', '.join(parts)}; {why}): figures from this scene are not comparable with the documents'"
    )


def main() -> None:
    """``python -m dvpmvs.evaluation.scene_digest [--record KEY] WORKSPACE``: print a rendered
    scene's digest and parts; with ``--record``, make it the reference render of KEY."""
    import argparse

    parser = argparse.ArgumentParser(description=main.__doc__.splitlines()[0])
    parser.add_argument("workspace", type=Path)
    parser.add_argument(
        "--record",
        metavar="KEY",
        help="record it as the reference render of KEY "
        "(room_8v_800_seed0: scene, views, width, scene seed)",
    )
    args = parser.parse_args()
    try:
        digest = scene_digest(args.workspace)
    except ValueError as exc:
        parser.error(str(exc))
    print(digest.short, json.dumps(digest.parts, indent=2))
    if args.record:
        record(args.record, digest)
        print(f"recorded as the reference render of {args.record} in {DOCUMENTED}")


if __name__ == "__main__":
    main()
