"""A rendered scene's identity: the digest of its content, the same on every vector path."""

import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import cv2
import pytest

from dvpmvs.evaluation.scene_digest import (
    SceneDigest,
    compare_with_documented,
    documented,
    scene_digest,
    vector_extensions,
)
from tests.helpers import dvpmvs


def _synth(out, env=None, scene="room", views=2, width=160):
    result = dvpmvs(
        "synth",
        f"out={out}",
        f"scene={scene}",
        f"views={views}",
        f"width={width}",
        "seed=0",
        cwd=Path(out).parent,
        env={**os.environ, **(env or {})},
    )
    assert result.returncode == 0, result.stderr[-2000:]
    return result


def _baseline_only() -> dict:
    """The environment that switches off every vector path this machine's OpenCV and numpy
    dispatch to at run time (their baselines stay: they are compiled in), and on x86-64 puts
    OpenBLAS on its generic kernels (Prescott: SSE3, no fused multiply-add)."""
    paths = vector_extensions()
    env = {
        "OPENCV_CPU_DISABLE": ",".join(paths["opencv"]),
        "NPY_DISABLE_CPU_FEATURES": " ".join(paths["numpy"]),
    }
    if platform.machine() in ("x86_64", "AMD64"):
        env["OPENBLAS_CORETYPE"] = "Prescott"
    return env


@pytest.mark.parametrize("scene", ["room", pytest.param("courtyard", marks=pytest.mark.slow)])
def test_a_scene_renders_the_same_content_on_every_vector_path(tmp_path, scene):
    env = _baseline_only()
    if not env["OPENCV_CPU_DISABLE"] and not env["NPY_DISABLE_CPU_FEATURES"]:
        pytest.skip("this machine dispatches to no vector path beyond the baselines")
    _synth(tmp_path / "a", scene=scene)
    _synth(tmp_path / "b", env, scene=scene)
    # The switch took effect in the child: it sees only the baselines.
    child = subprocess.run(
        [
            sys.executable,
            "-c",
            "import json; from dvpmvs.evaluation.scene_digest import "
            "vector_extensions as v; print(json.dumps(v()))",
        ],
        capture_output=True,
        text=True,
        env={**os.environ, **env},
        check=True,
    )
    assert json.loads(child.stdout) == {"opencv": [], "numpy": []}
    a, b = scene_digest(tmp_path / "a"), scene_digest(tmp_path / "b")
    assert set(a.parts) == {"images", "sparse", "ground_truth", "priors", "parameters"}
    assert a.differing(b) == [], a.differing(b)


def test_the_digest_is_of_the_content_and_names_the_part_that_differs(tmp_path):
    result = _synth(tmp_path / "s")
    digest = scene_digest(tmp_path / "s")
    assert "scene digest" in result.stderr and digest.short in result.stderr
    assert f"scene room_2v_160_seed0: digest {digest.short}" in result.stderr
    # PNG files: their pixels count, not their compression.
    image = tmp_path / "s" / "images" / "0000.png"
    pixels = cv2.imread(str(image), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(image), pixels, [cv2.IMWRITE_PNG_COMPRESSION, 0])
    assert scene_digest(tmp_path / "s").digest == digest.digest
    pixels[0, 0, 0] ^= 1
    cv2.imwrite(str(image), pixels)
    assert scene_digest(tmp_path / "s").differing(digest) == ["images"]
    # A run's maps in stereo/ are not the scene; its configuration files are.
    (tmp_path / "s" / "stereo" / "depth_maps").mkdir(exist_ok=True)
    (tmp_path / "s" / "stereo" / "depth_maps" / "x.bin").write_bytes(b"1")
    assert "sparse" not in scene_digest(tmp_path / "s").differing(digest)
    (tmp_path / "s" / "stereo" / "fusion.cfg").write_text("0000.png\n")
    assert "sparse" in scene_digest(tmp_path / "s").differing(digest)


def test_the_demo_scene_is_its_reference_render(tmp_path):
    from dvpmvs.evaluation.embedded import materialise

    digest = scene_digest(materialise(tmp_path / "demo"))
    entry = documented("room_5v_320_seed0")
    assert entry is not None and digest.differing(entry["parts"]) == [], compare_with_documented(
        "room_5v_320_seed0", digest
    )
    assert "the reference render" in compare_with_documented("room_5v_320_seed0", digest)


def test_a_scene_other_than_the_reference_says_what_differs():
    entry = documented("room_5v_320_seed0")
    other = SceneDigest({**entry["parts"], "ground_truth": "0" * 64})
    line = compare_with_documented("room_5v_320_seed0", other)
    assert "is NOT the reference render's" in line and "differing: ground_truth" in line
    assert "not comparable" in line
    assert "no reference render" in compare_with_documented("room_3v_64_seed9", other)


@pytest.mark.slow
def test_the_suite_room_renders_its_reference_digest(tmp_path):
    # One 800x600 suite scene, as `dvpmvs bench scene=room width=800` renders it.
    result = _synth(tmp_path / "room", views=8, width=800)
    digest = scene_digest(tmp_path / "room")
    assert digest.digest == documented("room_8v_800_seed0")["digest"], result.stderr[-500:]
    assert "the reference render" in result.stderr
