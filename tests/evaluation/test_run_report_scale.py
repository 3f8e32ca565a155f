"""report.html of a collection (issue 49 point 4, issue 52's report points): a fake workspace of
hundreds to thousands of views (scripts/bench/report_size.py) gives a page of bounded size whose
per-image table is sorted worst first and collapsed after its first rows."""

from __future__ import annotations

import importlib.util
import json
import re
import sys

from rotonly_cli.evaluation.run_report import SHOWN_ROWS

from helpers import REPOSITORY


def _report_size():
    spec = importlib.util.spec_from_file_location("bench_script_report_size",
                                                  REPOSITORY / "scripts" / "bench" / "report_size.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


report_size = _report_size()


def _rows(html: str) -> list[list[str]]:
    """The cells' text of every row of the per-image tables (shown, then collapsed)."""
    rows = []
    for table in re.findall(r'<table class="per-view">(.*?)</table>', html, flags=re.S):
        for row in re.findall(r"<tr>(.*?)</tr>", table, flags=re.S):
            cells = [re.sub(r"<[^>]+>", "", cell) for cell in re.findall(r"<td>(.*?)</td>", row, flags=re.S)]
            if cells:
                rows.append(cells)
    return rows


def test_per_image_table_with_gt_is_worst_first_and_collapsed(tmp_path):
    measured = report_size.measure(300, gt=True, keep=tmp_path)
    html = (tmp_path / "v300" / "report.html").read_text()
    rows = _rows(html)
    assert len(rows) == 300  # every image once
    head, _, rest = html.partition('<details id="per-view-rest">')
    assert len(_rows(head)) == SHOWN_ROWS == 50 and len(_rows(rest)) == 250
    assert "the other 250 images" in rest
    # the GT columns, labelled: the geodesic error sorts the rows, evalQuality's trace/3 beside it
    assert "rotation error, geodesic [deg]" in head and "evalQuality angle, acos(trace/3) [deg]" in head
    geodesic = [float(row[7]) for row in rows]
    assert geodesic == sorted(geodesic, reverse=True)
    evaluation = json.loads((tmp_path / "v300" / "eval" / "report.json").read_text())
    assert geodesic[0] == float(f"{max(c['rotation_error_deg'] for c in evaluation['per_camera']):.4g}")
    assert 0.0 < geodesic[-1] and geodesic[0] < 0.06  # the fake rotations are 0.01-0.05 deg off (then aligned)
    # the shown rows carry their sources; the collapsed ones are plain cells
    assert head.count('data-source="export.per_view.') == SHOWN_ROWS * 6
    assert 'data-source="export.per_view.' not in rest.split("</details>")[0]
    assert "<title>rotonly: v300/database.db</title>" in html
    assert '<p class="no-warnings" id="warnings">No warnings.</p>' in html
    eval_html = (tmp_path / "v300" / "eval" / "report.html").read_text()
    assert '<details id="per-camera-rest"><summary>the other 250 cameras' in eval_html
    assert measured["report_html_bytes"] < 1_300_000  # measured 1.06 MB (PNG figures of eval/ 0.6 MB)


def test_page_of_a_thousand_views_stays_small(tmp_path):
    measured = report_size.measure(1000, gt=False, keep=tmp_path)
    html = (tmp_path / "v1000" / "report.html").read_text()
    # no GT: unregistered first, then by the median reprojection error, worst first
    medians = [float(row[4]) for row in _rows(html)]
    assert len(medians) == 1000 and medians == sorted(medians, reverse=True)
    # a histogram over the images instead of 1000 bars; the view graph and top view sampled
    assert "histogram over the images" in html
    assert measured["report_html_bytes"] < 1_100_000  # measured 0.93 MB (before: 1.62 MB with GT)
