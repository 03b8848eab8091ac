"""The HTML report of a run and of a sweep (dvpmvs/report.py): what it links stays in the folder,
the cloud it carries is the run's, and (slow) a real browser draws it."""

import base64
import html
import json
import os
import shutil
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlparse

import numpy as np
import pytest

from dvpmvs.pointcloud import read_ply, write_point_cloud
from dvpmvs.report import ASSETS_DIR, REPORT_NAME
from tests.helpers import built_once, dvpmvs

# What a report holds does not depend on the maps' size: 80 px keeps each run short.
FAST = ["quality=fast", "max_image_size=80", "num_threads=2", "progress=false"]
DOCS = Path(__file__).resolve().parent.parent / "docs"
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


class _Links(HTMLParser):
    """Every URL a page names (href, src) and the ids of its elements."""

    def __init__(self):
        super().__init__()
        self.urls, self.ids = [], set()

    def handle_starttag(self, tag, attrs):
        for name, value in attrs:
            if name in ("href", "src", "data-src") and value is not None:
                self.urls.append(value)
            if name == "id":
                self.ids.add(value)


def _links(page: Path) -> _Links:
    parser = _Links()
    parser.feed(page.read_text())
    return parser


def _assert_links_stay_in(page: Path, folder: Path):
    links = _links(page)
    assert links.urls
    for url in links.urls:
        parsed = urlparse(url)
        if not parsed.path and parsed.fragment:
            continue  # an anchor of the page itself
        assert not parsed.scheme and not parsed.netloc and not url.startswith("/"), url
        target = (page.parent / unquote(parsed.path)).resolve()
        assert target.is_relative_to(folder.resolve()), url
        assert target.is_file(), url
    return links


def _cloud_data(script: Path) -> dict:
    text = script.read_text()
    return json.loads(text[text.index("] = ") + 4 :].rstrip().rstrip(";"))


def _synth(folder: Path) -> Path:
    """A 4-view synthetic room of 160x120, with its ground truth."""
    result = dvpmvs(
        "synth", f"out={folder}", "scene=room", "views=4", "width=160", "seed=3", cwd=folder.parent
    )
    assert result.returncode == 0, result.stderr[-2000:]
    return folder


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A dense run (quality=fast) on a synthetic scene into its own folder, previews on, scored."""

    def build(root: Path) -> None:
        ws = _synth(root / "ws")
        result = dvpmvs("dense", f"workspace={ws}", f"out={root / 'out'}", *FAST, cwd=root)
        assert result.returncode == 0, result.stderr[-2000:]

    return built_once(tmp_path_factory, "report_run", build) / "out"


@pytest.mark.slow
def test_a_dense_run_writes_a_report_whose_every_link_is_a_file_of_its_folder(run):
    page = run / REPORT_NAME
    links = _assert_links_stay_in(page, run)
    assert {"run", "timing", "scores", "cloud", "views"} <= links.ids
    previews = {u for u in links.urls if "/previews/" in u}
    # each of the 4 views: depth, normal and cost of both passes, and its priors' 4 pictures
    assert len(previews) == 4 * 10, sorted(previews)
    assert len({u for u in links.urls if u.startswith(f"{ASSETS_DIR}/images/")}) == 4  # the photos
    text = page.read_text()
    assert "http://" not in text and "https://" not in text
    # scored against the scene's ground truth: the scores' curve drawn, the coloured clouds carried
    assert "<svg" in text and (run / "evaluation" / "fused_f1.json").is_file()
    for asset in ("three.bundle.js", "viewer.js", "report.css", "LICENSE.three.txt"):
        assert (run / ASSETS_DIR / asset).is_file()


def test_the_report_carries_the_runs_cloud_and_its_cameras(run):
    data = _cloud_data(run / ASSETS_DIR / "cloud.js")
    fused = read_ply(run / "fused.ply")
    cloud = data["sets"][0]
    assert cloud["count"] == cloud["total"] == len(fused) > 100
    positions = np.frombuffer(base64.b64decode(cloud["positions"]), "<f4").reshape(-1, 3)
    # centred on the cloud's median: the same points, shifted
    shift = np.median(fused.points, axis=0)
    assert np.allclose(positions + shift, fused.points, atol=1e-4 * np.abs(fused.points).max())
    rgb = np.frombuffer(base64.b64decode(cloud["colours"]["rgb"]), np.uint8).reshape(-1, 3)
    assert np.array_equal(rgb, np.round(fused.colors * 255).astype(np.uint8))
    assert "views" in cloud["colours"]  # from fused.ply.vis
    assert [s["label"] for s in data["sets"][1:]] == [
        "evaluation: accuracy at 0.02 m",
        "evaluation: completeness at 0.02 m",
    ]
    frusta = np.frombuffer(base64.b64decode(data["frusta"]), "<f4").reshape(-1, 3)
    assert len(frusta) == 4 * 8 * 2  # 4 cameras, 8 segments each


def test_dvpmvs_report_rewrites_a_report_with_a_bound_on_the_points(run, tmp_path):
    folder = tmp_path / "copy"
    shutil.copytree(run, folder, symlinks=True)
    result = dvpmvs("report", str(folder), "--max-points", "100", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    cloud = _cloud_data(folder / ASSETS_DIR / "cloud.js")["sets"][0]
    assert cloud["count"] == 100 and cloud["total"] == len(read_ply(folder / "fused.ply"))
    assert "100 of" in (folder / REPORT_NAME).read_text()
    # the same subsample every time
    first = (folder / ASSETS_DIR / "cloud.js").read_bytes()
    assert dvpmvs("report", str(folder), "--max-points", "100", cwd=tmp_path).returncode == 0
    assert (folder / ASSETS_DIR / "cloud.js").read_bytes() == first


NAMES = ["café #1.png", "100%41 done?.png", "IMG[1].png", "a/x.png", "b/x.png"]


def test_the_views_table_links_every_file_whatever_its_name(tmp_path):
    import cv2

    from dvpmvs.report import write_run_report

    # A run folder as dense leaves it, with names COLMAP allows: '#', '%', '?', '[', subfolders.
    folder = tmp_path / "run"
    for i, name in enumerate(NAMES):
        image = np.full((30, 40, 3), 40 * i, np.uint8)
        for path in (
            folder / "images" / name,
            folder / "stereo" / "previews" / f"{name}.photometric.depth.png",
        ):
            path.parent.mkdir(parents=True, exist_ok=True)
            assert cv2.imwrite(str(path.with_suffix(".tmp.png")), image)
            path.with_suffix(".tmp.png").rename(path)
        record = folder / "stereo" / "provenance" / f"{name}.photometric.json"
        record.parent.mkdir(parents=True, exist_ok=True)
        reference = {"name": name, "K": np.eye(3).tolist(), "R": np.eye(3).tolist(), "t": [i, 0, 0]}
        record.write_text(
            json.dumps(
                {
                    "state": "complete",
                    "inputs": {"pass": "photometric", "reference": {**reference, "size": [40, 30]}},
                    "stats": {"seconds": 1.0},
                }
            )
        )
    page = write_run_report(folder)
    links = _assert_links_stay_in(page, folder)  # every link is a file of the folder
    text = page.read_text()
    for name in NAMES:  # each view's row, its photo and its preview
        assert f"<td>{html.escape(name)}</td>" in text, name
        assert f"stereo/previews/{name}.photometric.depth.png" in {unquote(u) for u in links.urls}
    assert len([u for u in links.urls if "report_files/images/" in u]) >= 2 * len(NAMES)


@pytest.mark.parametrize(
    "text, needle",
    [
        ("\x00garbage", "is not a JSON object"),
        ("[1, 2]", "is not a JSON object"),
        ('{"dense": "x"}', "holds a str as 'dense'"),
        ('{"dense": {"fusion": []}}', "holds a list as 'dense.fusion'"),
        ('{"command": "dvpmvs dense"}', "holds a str as 'command'"),
    ],
)
def test_a_garbled_manifest_is_named_not_a_traceback(run, tmp_path, text, needle):
    folder = tmp_path / "copy"
    shutil.copytree(run, folder, symlinks=True)
    (folder / "dvpmvs_run.json").write_text(text)
    result = dvpmvs("report", str(folder), cwd=tmp_path)
    said = " ".join(result.stderr.split())
    assert result.returncode == 1 and needle in said and "dvpmvs_run.json" in said, said
    assert "Traceback" not in result.stderr


def test_the_views_table_shows_the_views_of_this_run_only(run, tmp_path):
    # An out folder an earlier run wrote to keeps that run's records: here the manifest says this
    # run had two of the four views.
    folder = tmp_path / "copy"
    shutil.copytree(run, folder, symlinks=True)
    manifest = json.loads((folder / "dvpmvs_run.json").read_text())
    for figures in manifest["dense"]["passes"].values():
        figures["view_reports"] = figures["view_reports"][:2]
    ran = [r["name"] for r in manifest["dense"]["passes"]["photometric"]["view_reports"]]
    (folder / "dvpmvs_run.json").write_text(json.dumps(manifest))
    assert dvpmvs("report", str(folder), cwd=tmp_path).returncode == 0
    rows = (folder / REPORT_NAME).read_text().split('id="views"')[1]
    shown = [
        name
        for name in ("0000.png", "0001.png", "0002.png", "0003.png")
        if f"<td>{name}</td>" in rows
    ]
    assert shown == ran


def test_a_copied_run_folder_shows_its_own_cloud(run, tmp_path):
    # The manifest names the run's files relative to its folder, not to where the command ran.
    manifest = json.loads((run / "dvpmvs_run.json").read_text())
    assert manifest["dense"]["fusion"]["output"] == "fused.ply"
    assert manifest["dense"]["stereo_dir"] == "stereo"
    folder = tmp_path / "copy"
    shutil.copytree(run, folder, symlinks=True)
    fused = read_ply(folder / "fused.ply")
    half = len(fused.points) // 2  # the copy's cloud is not the run's
    write_point_cloud(folder / "fused.ply", fused.points[:half], fused.colors[:half])
    result = dvpmvs("report", str(folder), cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert _cloud_data(folder / ASSETS_DIR / "cloud.js")["sets"][0]["total"] == half


@pytest.mark.parametrize(
    "args,needle",
    [
        (["/nonexistent/run"], "is not a folder"),
        (["."], "holds no run"),
        (["RUN", "--max-points", "0"], "max_points=0"),
        (["RUN", "--max-pointz", "5"], "see `dvpmvs report --help`"),
    ],
)
def test_dvpmvs_report_on_bad_input_says_what_to_do(run, tmp_path, args, needle):
    args = [str(run) if a == "RUN" else a for a in args]
    result = dvpmvs("report", *args, cwd=tmp_path)
    assert (
        result.returncode == 1 and needle in result.stderr and "Traceback" not in result.stderr
    ), result.stderr


def test_a_report_html_dvpmvs_did_not_write_is_replaced_only_with_overwrite(run, tmp_path):
    folder = tmp_path / "copy"
    shutil.copytree(run, folder, symlinks=True)
    (folder / REPORT_NAME).write_text("<html>my own notes</html>")
    result = dvpmvs("report", str(folder), cwd=tmp_path)
    assert (
        result.returncode == 1
        and "dvpmvs did not write it" in result.stderr
        and "--overwrite" in result.stderr
    )
    assert (folder / REPORT_NAME).read_text() == "<html>my own notes</html>"
    # a dense run there keeps its outputs, warns and leaves the page
    result = dvpmvs("dense", f"workspace={run.parent / 'ws'}", f"out={folder}", *FAST, cwd=tmp_path)
    assert result.returncode == 0 and "dvpmvs did not write it" in result.stdout + result.stderr, (
        result.stderr[-2000:]
    )
    assert (folder / REPORT_NAME).read_text() == "<html>my own notes</html>"
    assert dvpmvs("report", str(folder), "--overwrite", cwd=tmp_path).returncode == 0
    assert "dvpmvs report" in (folder / REPORT_NAME).read_text()


@pytest.mark.slow
def test_a_cloud_written_outside_the_run_folder_is_shown_from_the_pages_copy(run, tmp_path):
    result = dvpmvs(
        "dense",
        f"workspace={run.parent / 'ws'}",
        f"out={tmp_path / 'out'}",
        f"output={tmp_path / 'elsewhere' / 'cloud.ply'}",
        *FAST,
        "previews=false",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    page = tmp_path / "out" / REPORT_NAME
    _assert_links_stay_in(page, tmp_path / "out")
    assert f"<code>{tmp_path / 'elsewhere' / 'cloud.ply'}</code>" in page.read_text()
    cloud = _cloud_data(tmp_path / "out" / ASSETS_DIR / "cloud.js")["sets"][0]
    assert cloud["total"] == len(read_ply(tmp_path / "elsewhere" / "cloud.ply")) > 1000


@pytest.mark.slow
def test_report_false_writes_no_report_and_a_json_path_writes_both(tmp_path):
    _synth(tmp_path / "ws")
    result = dvpmvs(
        "dense",
        f"workspace={tmp_path / 'ws'}",
        f"out={tmp_path / 'a'}",
        *FAST,
        "report=false",
        "previews=false",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert (
        not (tmp_path / "a" / REPORT_NAME).exists() and not (tmp_path / "a" / ASSETS_DIR).exists()
    )
    result = dvpmvs(
        "dense",
        f"workspace={tmp_path / 'ws'}",
        f"out={tmp_path / 'a'}",
        *FAST,
        "previews=false",
        f"report={tmp_path / 'run.json'}",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert (tmp_path / "a" / REPORT_NAME).is_file() and json.loads(
        (tmp_path / "run.json").read_text()
    )["status"] == "ok"
    result = dvpmvs("dense", f"workspace={tmp_path / 'ws'}", *FAST, "report=run.txt", cwd=tmp_path)
    assert result.returncode == 1 and "report=run.txt: give true" in result.stderr, result.stderr[
        -2000:
    ]


# -- in a real browser -----------------------------------------------------------------------------


def _open_in_chromium(
    page_path: Path,
    screenshot: Path,
    element: str,
    picture: Path | None = None,
    script: str | None = None,
):
    """Open ``page_path`` from disk in headless Chromium with every request that is not a file
    refused; returns (console errors and page errors, requests that left the disk, the screenshot
    of each ``element`` as an array, per thumbnail whether it loaded). ``picture``: also a
    picture of the page from the cloud to the first view's maps (README's). ``script``: run in
    the page before the screenshots."""
    playwright = pytest.importorskip("playwright.sync_api")
    from PIL import Image

    problems, outside = [], []
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=CHROMIUM,
            args=[
                "--headless=new",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--no-first-run",
                "--disable-quic",
                "--disable-dev-shm-usage",
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
            ],
        )
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        page.on(
            "console",
            lambda m: problems.append(f"console {m.type}: {m.text}") if m.type == "error" else None,
        )
        page.on("pageerror", lambda e: problems.append(f"page error: {e}"))

        def route(request_route):
            if request_route.request.url.startswith("file://"):
                request_route.continue_()
            else:
                outside.append(request_route.request.url)
                request_route.abort()

        page.route("**/*", route)
        page.goto(page_path.resolve().as_uri())
        page.wait_for_selector("body[data-ready=yes]", timeout=120_000)
        page.wait_for_timeout(500)
        # thumbnails load lazily, when scrolled to: load each now and see that it decodes
        loaded = page.eval_on_selector_all(
            "a.thumb img",
            "imgs => Promise.all(imgs.map(i => { i.loading = 'eager'; "
            "return i.decode().then(() => i.naturalWidth > 0, () => false); }))",
        )
        if script is not None:
            page.evaluate(script)
            page.wait_for_timeout(300)
        shots = []
        for i in range(page.locator(element).count()):
            path = screenshot.with_name(
                f"{screenshot.stem}{'' if i == 0 else i}{screenshot.suffix}"
            )
            page.locator(element).nth(i).screenshot(path=str(path))
            shots.append(np.asarray(Image.open(path).convert("RGB")))
        if picture is not None:
            page.evaluate("window.scrollTo(0, 0)")
            top = page.locator("#cloud").bounding_box()
            row = page.locator("#views tbody tr").first.bounding_box()
            page.screenshot(
                path=str(picture),
                full_page=True,
                type="jpeg",
                quality=85,
                clip={
                    "x": 0,
                    "y": top["y"],
                    "width": 1280,
                    "height": row["y"] + row["height"] - top["y"],
                },
            )
        browser.close()
    return problems, outside, shots, loaded


def _drawn_fraction(pixels: np.ndarray) -> float:
    """The share of the canvas's pixels that are not its background (#15181d)."""
    return float(np.mean(np.abs(pixels.astype(int) - [0x15, 0x18, 0x1D]).sum(axis=2) > 30))


@pytest.mark.slow
@pytest.mark.skipif(
    CHROMIUM is None,
    reason="no Chromium (Debian's chromium package; scripts/system-deps.sh --test)",
)
def test_the_demos_report_draws_its_cloud_and_maps_in_chromium(demo_run, tmp_path):
    assert demo_run.returncode == 0, demo_run.stderr[-2000:]
    page = demo_run.cwd / "dvpmvs_demo" / REPORT_NAME
    _assert_links_stay_in(page, demo_run.cwd / "dvpmvs_demo")
    picture = DOCS / "images" / "report.jpg" if os.environ.get("DVPMVS_UPDATE_SCREENSHOT") else None
    problems, outside, shots, loaded = _open_in_chromium(
        page, tmp_path / "cloud.png", "#cloud .viewer canvas", picture
    )
    assert problems == [] and outside == [] and len(shots) == 1
    cloud = shots[0]
    assert len(loaded) == 5 * 12 and all(loaded)  # each view: photo, 4 priors, 6 maps, depth error
    drawn = _drawn_fraction(cloud)
    assert 0.25 < drawn < 0.40, (
        drawn
    )  # measured 0.31: the room seen from a step behind the first camera
    assert cloud.reshape(-1, 3).std(axis=0).min() > 20  # colours, not one flat colour


@pytest.mark.slow
def test_a_three_job_bench_sweeps_report_shows_the_three_clouds_in_chromium(tmp_path):
    result = dvpmvs(
        "bench",
        "-m",
        "scene=room",
        "views=4",
        "width=160",
        "quality=fast",
        "num_threads=2",
        "max_image_size=96,128,160",
        f"scenes_dir={tmp_path / 'scenes'}",
        f"hydra.sweep.dir={tmp_path / 'sweep'}",
        "progress=false",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    sweep = tmp_path / "sweep"
    page = sweep / REPORT_NAME
    # The sweep's page links each job's report and cloud, each job's page stays in its folder.
    links = _assert_links_stay_in(page, sweep)
    assert {f"{job}/report.html" for job in "012"} | {
        f"{job}/{ASSETS_DIR}/cloud.js" for job in "012"
    } <= set(links.urls)
    for job in "012":
        _assert_links_stay_in(sweep / job / REPORT_NAME, sweep / job)
    assert "max_image_size" in page.read_text()
    if CHROMIUM is None:
        pytest.skip(
            "the links were checked; no Chromium to draw the clouds (Debian's chromium package; "
            "scripts/system-deps.sh --test)"
        )
    problems, outside, canvases, _ = _open_in_chromium(
        page, tmp_path / "cloud.png", "#compare canvas"
    )
    assert problems == [] and outside == [] and len(canvases) == 3
    # side by side, from the same point of view: the larger the maps, the more points, the more pixels
    drawn = [_drawn_fraction(canvas) for canvas in canvases]
    assert 0.06 < drawn[0] < drawn[1] < drawn[2] < 0.40, drawn  # measured 0.10, 0.22, 0.30


def test_eval_in_a_run_folder_keeps_the_runs_page_and_files_it_did_not_write(run, tmp_path):
    folder = tmp_path / "run"
    shutil.copytree(run, folder)
    page, cloud = (
        (folder / REPORT_NAME).read_bytes(),
        (folder / ASSETS_DIR / "cloud.js").read_bytes(),
    )
    gt = run.parent / "ws" / "ground_truth" / "scan_alignment.mlp"
    scored = (f"reconstruction={folder / 'fused.ply'}", f"ground_truth={gt}", "tolerances=[0.05]")
    # A page of its own beside the run's: its cloud in a file of its own.
    result = dvpmvs("eval", *scored, f"report={folder / 's.json'}", cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    assert (folder / ASSETS_DIR / "s.cloud.js").is_file() and (folder / "s.html").is_file()
    assert (folder / ASSETS_DIR / "cloud.js").read_bytes() == cloud
    # Named like the run's page: the scores are written, the run's page is not replaced.
    result = dvpmvs("eval", *scored, f"report={folder / 'report.json'}", cwd=tmp_path)
    said = " ".join((result.stdout + result.stderr).split())
    assert result.returncode == 0 and "is a run's report" in said
    assert (folder / REPORT_NAME).read_bytes() == page
    # A JSON file dvpmvs did not write is not replaced unasked, before anything is scored.
    mine = tmp_path / "my.json"
    mine.write_text('{"mine": 1}')
    result = dvpmvs("eval", *scored, f"report={mine}", cwd=tmp_path)
    assert result.returncode == 1 and "dvpmvs did not write it" in " ".join(result.stderr.split())
    assert json.loads(mine.read_text()) == {"mine": 1}
    result = dvpmvs("eval", *scored, f"report={mine}", "overwrite=true", cwd=tmp_path)
    assert result.returncode == 0 and "f1" in json.loads(mine.read_text())


def test_eval_writes_its_report_beside_its_json(run, tmp_path):
    gt = run.parent / "ws" / "ground_truth" / "scan_alignment.mlp"
    result = dvpmvs(
        "eval",
        f"reconstruction={run / 'fused.ply'}",
        f"ground_truth={gt}",
        "tolerances=[0.02,0.1]",
        "report=ev/scores.json",
        "plot=ev/f1.png",
        "clouds=ev/clouds",
        cwd=tmp_path,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    page = tmp_path / "ev" / "scores.html"
    links = _assert_links_stay_in(page, tmp_path / "ev")
    assert {"run", "scores", "cloud"} <= links.ids
    text = page.read_text()
    scores = json.loads((tmp_path / "ev" / "scores.json").read_text())
    assert (
        f"<b>{100 * scores['f1'][0]:.2f}</b>" in text and "<svg" in text
    )  # the table and the drawn curve
    data = _cloud_data(tmp_path / "ev" / ASSETS_DIR / "scores.cloud.js")
    assert [s["label"] for s in data["sets"]] == [
        "scored cloud",
        "evaluation: accuracy at 0.02 m",
        "evaluation: completeness at 0.02 m",
    ]
    assert data["sets"][0]["total"] == scores["reconstruction_points"]


def test_a_sweeps_page_draws_the_defaults_cloud_among_those_it_shows_first():
    from dvpmvs.report import CLOUDS_SHOWN, _clouds_shown_first

    # The README's ablation sweep: four jobs, the default last: all four drawn.
    four = [{"label": f"method={m}"} for m in ("paper", "w_o_agn", "w_o_mon", "default")]
    assert _clouds_shown_first(four) == {0, 1, 2, 3}
    # A larger sweep: the default's job and the first others, CLOUDS_SHOWN in all.
    methods = ("paper", "w_o_agn", "w_o_mon", "w_o_ero", "w_o_fil", "default")
    six = [{"label": f"scene=room method={m}"} for m in methods]
    assert _clouds_shown_first(six) == {5, 0, 1, 2} and CLOUDS_SHOWN == 4


def test_every_map_preview_carries_its_colour_bar_and_range():
    from dvpmvs.report import ViewRow, _views_section

    row = ViewRow("0000.png", depth_range=(1.25, 6.5))
    row.images = [
        ("image", "images/0000.png"),
        ("geometric depth", "stereo/previews/0000.png.geometric.depth.png"),
        ("geometric cost", "stereo/previews/0000.png.geometric.cost.png"),
        ("geometric normal", "stereo/previews/0000.png.geometric.normal.png"),
        ("depth error", "evaluation/error_maps/0000.error.png"),
    ]
    html = _views_section([row])
    figures = html.split("<figure>")[1:]
    assert 'class="legend"' not in figures[0]  # the photo has none
    assert "<span>1.25</span>" in figures[1] and "<span>6.5</span>" in figures[1]
    assert "rgb(" in figures[1]  # the turbo map the depth previews are drawn with
    assert "1 (1 - NCC)" in figures[2] and "x, y, z: red, green, blue" in figures[3]
    assert "5 %+; blue: none" in figures[4]
