"""OUT/report.html: written on every run, self-contained, its numbers those of reports/*.json,
and every figure loads in a real browser (headless Chromium, skipped where it is not installed)."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import subprocess
import tempfile
from html import unescape
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from rotonly_cli.evaluation import svg
from rotonly_cli.evaluation.run_report import top_view_axes
from rotonly_cli.pipeline import STAGES

from helpers import DATA_FIXTURES, rotonly

HERZ_JESU = DATA_FIXTURES / "herzjesu_p8"


@pytest.fixture(scope="module")
def full_run(tmp_path_factory):
    """`rotonly run` with --gt on the Herz-Jesu database fixture."""
    out = tmp_path_factory.mktemp("report") / "out"
    assert rotonly("-q", "run", HERZ_JESU / "database.db", "-o", out, "--gt", HERZ_JESU) == 0
    return out


class _Page(HTMLParser):
    """The images and the report-sourced numbers (``data-source``) of a page."""

    def __init__(self):
        super().__init__()
        self.images: list[dict] = []
        self.sources: list[tuple[str, str]] = []
        self.resources: list[str] = []
        self._source: str | None = None
        self._text = ""

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "img":
            self.images.append(attrs)
        if tag in ("script", "link", "iframe", "img") and (attrs.get("src") or attrs.get("href")):
            self.resources.append(attrs.get("src") or attrs.get("href"))
        if "data-source" in attrs:
            self._source, self._text = attrs["data-source"], ""

    def handle_data(self, data):
        if self._source is not None:
            self._text += data

    def handle_endtag(self, tag):
        if tag == "span" and self._source is not None:
            self.sources.append((self._source, self._text))
            self._source = None


def _page(path: Path) -> _Page:
    page = _Page()
    page.feed(path.read_text())
    return page


def _reports(out: Path) -> dict:
    return {p.stem: json.loads(p.read_text()) for p in (out / "reports").glob("*.json")}


def _lookup(reports: dict, path: str):
    value = reports
    for key in path.split("."):
        value = value[int(key)] if isinstance(value, list) else value[key]
    return value


def _matches(shown: str, value, path: str = "") -> bool:
    if path.endswith("time_s") and isinstance(value, (int, float)):  # seconds to the millisecond
        return shown == f"{value:.3f}"
    if value is None:
        return shown == "–"
    if isinstance(value, bool):
        return shown == ("yes" if value else "no")
    if isinstance(value, int):
        return shown == str(value)
    if isinstance(value, float):
        return math.isclose(float(shown), value, rel_tol=5e-4, abs_tol=1e-300)
    return shown == str(value)


def test_report_is_self_contained_and_its_numbers_are_the_reports(full_run):
    page = _page(full_run / "report.html")
    assert all(src.startswith("data:image/") for src in page.resources), page.resources
    assert len(page.images) >= 6 + 4  # run figures + the four eval figures of --gt
    reports = _reports(full_run)
    assert {"load", "identify", "refine", "average", "optimize", "translate", "triangulate", "export",
            "run"} <= set(reports)
    shown = dict(page.sources)
    assert len(page.sources) > 200
    for path, text in page.sources:
        assert _matches(text, _lookup(reports, path), path), (path, text)
    # the summary and the times are there
    for path in ("run.num_registered", "run.num_views", "run.num_points", "run.num_active_edges", "load.num_pairs",
                 "export.num_observations", "export.reprojection_error_px.median", "run.rotation_error_deg.mean",
                 "run.time_s", *(f"{name}.time_s" for name in reports if name not in ("run", "resources")),
                 *(f"resources.{name}.peak_rss_mb" for name in reports["resources"])):
        assert path in shown, path
    # per image: every view's observation count and errors
    for k, view in enumerate(reports["export"]["per_view"]):
        assert shown[f"export.per_view.{k}.num_observations"] == str(view["num_observations"])
    assert sum(v["num_observations"] for v in reports["export"]["per_view"]) == reports["export"]["num_observations"]
    assert sum(reports["export"]["track_lengths"].values()) == reports["export"]["num_points"] \
        == reports["run"]["num_points"]


def test_report_names_the_input_the_command_and_the_gt_errors_per_image(full_run):
    html = (full_run / "report.html").read_text()
    run = _reports(full_run)["run"]
    assert "<title>rotonly: herzjesu_p8/database.db</title>" in html
    assert run["command"] == f"rotonly -q run {HERZ_JESU / 'database.db'} -o {full_run} --gt {HERZ_JESU}"
    assert f"Command: <code>{run['command']}</code>" in html
    assert run["options"]["gt"] == str(HERZ_JESU) and run["options"]["load"]["min_inliers"] == 30
    assert '<details id="options">' in html
    # 8 views, all shown: worst geodesic error first, evalQuality's trace/3 angle labelled beside it
    evaluation = json.loads((full_run / "eval" / "report.json").read_text())
    worst = max(evaluation["per_camera"], key=lambda c: c["rotation_error_deg"])
    table = html.split('<table class="per-view">')[1].split("</table>")[0]
    assert "rotation error, geodesic [deg]</th><th>evalQuality angle, acos(trace/3) [deg]" in table
    assert table.split("</tr>")[1].startswith(f"\n<tr><td>{worst['name']}</td>")
    assert "per-view-rest" not in html  # no more than SHOWN_ROWS images: nothing collapsed
    assert ("No warnings." in html) == (not run["warnings"])


def test_export_statistics_are_the_reprojection_errors(full_run):
    """reports/export.json: the distance between each observation and its point's projection."""
    from rotonly_cli.io import openmvg

    scene = openmvg.read_sfm_data(full_run / "sfm_data.json")
    errors = []
    for point, observations, pixels in zip(scene.structure.points, scene.structure.observations,
                                           scene.structure.observation_pixels):
        for (view_id, _), pixel in zip(observations, pixels):
            pose = scene.poses[view_id]
            intrinsics = scene.intrinsics[scene.views[view_id].intrinsics_id]  # a pinhole (COLMAP input)
            f, cx, cy = intrinsics.params[:3]
            x = pose.R_cam_from_world @ (point - pose.center)
            errors.append(np.linalg.norm(f * x[:2] / x[2] + [cx, cy] - pixel))
    report = json.loads((full_run / "reports" / "export.json").read_text())
    np.testing.assert_allclose(report["reprojection_error_px"]["median"], np.median(errors), rtol=1e-6)
    np.testing.assert_allclose(report["reprojection_error_px"]["max"], np.max(errors), rtol=1e-6)
    assert report["num_observations"] == len(errors)


CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]
#: after the page's load event, every image's state goes into the DOM that --dump-dom prints
PROBE = """<script>window.addEventListener('load', function () {
  var images = Array.from(document.images).map(function (i) { return [i.alt, i.complete, i.naturalWidth]; });
  var out = document.createElement('pre'); out.id = 'image-probe'; out.textContent = JSON.stringify(images);
  document.body.appendChild(out);
});</script>"""


def chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    return None


#: what a reader sees first: the tab's title, and the warnings box (or the "No warnings." line)
#: with its items, whether it is drawn, and whether it comes before the summary
HEAD_PROBE = """<script>window.addEventListener('load', function () {
  var box = document.getElementById('warnings');
  var summary = Array.from(document.querySelectorAll('h2')).find(function (h) { return h.textContent === 'Summary'; });
  var facts = {title: document.title, warnings: box && {
    className: box.className, text: box.innerText, drawn: box.offsetHeight > 0,
    items: Array.from(box.querySelectorAll('li')).map(function (li) { return li.textContent; }),
    beforeSummary: !!summary && !!(box.compareDocumentPosition(summary) & Node.DOCUMENT_POSITION_FOLLOWING)}};
  var out = document.createElement('pre'); out.id = 'image-probe'; out.textContent = JSON.stringify(facts);
  document.body.appendChild(out);
});</script>"""


def browser_probe(page: Path, script: str = PROBE):
    """What ``script`` (run after the load event) writes into ``<pre id="image-probe">``, as
    headless Chromium renders ``page``."""
    with tempfile.TemporaryDirectory() as scratch:
        probe = Path(scratch) / "probe.html"
        probe.write_text(page.read_text().replace("</body>", script + "</body>"))
        command = [chromium(), *CHROMIUM_FLAGS, f"--user-data-dir={scratch}/profile", "--dump-dom", probe.as_uri()]
        if os.geteuid() != 0:
            command.remove("--no-sandbox")
        dom = subprocess.run(command, capture_output=True, text=True, timeout=120, check=True).stdout
    found = re.search(r'<pre id="image-probe">(.*?)</pre>', dom, re.S)
    assert found, dom[-2000:]
    return json.loads(unescape(found.group(1)))


def browser_images(page: Path) -> list:
    """[alt, complete, naturalWidth] of every image of ``page`` as headless Chromium loads it."""
    return browser_probe(page, PROBE)


@pytest.mark.skipif(chromium() is None, reason="headless Chromium not installed (Debian: apt-get install chromium)")
def test_every_figure_loads_in_chromium(full_run, tmp_path):
    images = browser_images(full_run / "report.html")
    assert len(images) == len(_page(full_run / "report.html").images) >= 10
    assert all(complete and width > 0 for _, complete, width in images), images
    # the probe tells a broken figure from a loaded one
    broken = tmp_path / "broken.html"
    broken.write_text((full_run / "report.html").read_text().replace(
        "</h1>", '</h1><img alt="broken" src="data:image/svg+xml;base64,PHN2Zz4=">', 1))
    assert [width for alt, _, width in browser_images(broken) if alt == "broken"] == [0]


@pytest.mark.skipif(chromium() is None, reason="headless Chromium not installed (Debian: apt-get install chromium)")
def test_title_and_warnings_box_as_a_browser_shows_them(full_run, tmp_path):
    """The tab's title names the input; the warnings come first, before the summary: "No
    warnings." on a clean run, a box of items on a run with warnings (here a GT of another
    scene, issue 52)."""
    clean = browser_probe(full_run / "report.html", HEAD_PROBE)
    assert clean["title"] == "rotonly: herzjesu_p8/database.db"
    assert clean["warnings"] == {"className": "no-warnings", "text": "No warnings.", "drawn": True, "items": [],
                                 "beforeSummary": True}
    warned_out = tmp_path / "warned"
    assert rotonly("-q", "run", HERZ_JESU / "database.db", "-o", warned_out,
                   "--gt", DATA_FIXTURES / "evalquality" / "fountain-P11") == 0
    warned = browser_probe(warned_out / "report.html", HEAD_PROBE)
    box = warned["warnings"]
    assert warned["title"] == "rotonly: herzjesu_p8/database.db"
    assert box["className"] == "warnings" and box["drawn"] and box["beforeSummary"]
    assert box["text"].startswith("Warnings")
    assert box["items"] == _reports(warned_out)["run"]["warnings"]
    assert any(item.startswith("--gt: 3 of the 11 GT cameras name none") for item in box["items"])


def test_report_after_identify_and_stage_commands(tmp_path):
    db = tmp_path / "database.db"
    shutil.copyfile(HERZ_JESU / "database.db", db)
    out = tmp_path / "out"
    assert rotonly("-q", "identify", db, "-o", out) == 0
    page = _page(out / "report.html")
    assert [img["alt"] for img in page.images] == ["View graph (views on a circle in id order)"]
    assert "export" not in _reports(out)
    for stage in STAGES[2:]:
        assert rotonly("-q", stage, out) == 0
    page = _page(out / "report.html")
    assert len(page.images) == 6
    reports = _reports(out)
    for path, text in page.sources:
        assert _matches(text, _lookup(reports, path), path), (path, text)
    # after a stage command the later stages' reports of the earlier run are stale: not shown
    assert rotonly("-q", "refine", out) == 0
    sources = {path.split(".")[0] for path, _ in _page(out / "report.html").sources}
    assert {"load", "identify", "refine", "run"} <= sources and not sources & {"average", "export", "triangulate"}


def test_nice_ticks_and_top_view_axes():
    assert svg.nice_ticks(0, 1) == [0.0, 0.2, 0.4, 0.6, 0.8, 1.0]
    assert svg.nice_ticks(0.013, 0.087, 4) == [0.025, 0.05, 0.075]
    assert svg.nice_ticks(5, 5) and svg.nice_ticks(float("nan"), 1) == []
    axes = top_view_axes(np.eye(3)[None])  # camera looking along +z, image y down: up is -y
    np.testing.assert_allclose(axes, [[1, 0, 0], [0, 0, 1]], atol=1e-12)
