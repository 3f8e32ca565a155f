"""OpenMVG input as OpenMVG's own tools see it: ``root_path`` resolved from the current
directory (the sfm_data.json folder as a fallback) and written back as it came; ``-M/--matches``
chooses the matches file, and reports/load.json lists every file read."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from helpers import DATA_FIXTURES, rotonly

PROJECT = DATA_FIXTURES / "herzjesu_p8" / "openmvg"


def _project(folder, root_path: str):
    """A copy of the Herz-Jesu OpenMVG fixture in ``folder`` with ``root_path`` set."""
    shutil.copytree(PROJECT, folder)
    document = json.loads((folder / "sfm_data.json").read_text())
    document["root_path"] = root_path
    (folder / "sfm_data.json").write_text(json.dumps(document, indent=4))
    return [item["value"]["ptr_wrapper"]["data"]["filename"] for item in document["views"]]


def _images(folder, names) -> None:
    """Small plain-coloured JPEGs under the views' names (keypoints outside are clamped)."""
    import cv2

    folder.mkdir(parents=True)
    for name in names:
        cv2.imwrite(str(folder / name), np.full((16, 16, 3), (40, 90, 200), dtype=np.uint8))


@pytest.mark.parametrize("where", ["cwd", "beside"])
def test_root_path_found_the_openmvg_way_and_written_back(tmp_path, monkeypatch, where):
    """SfMInit_ImageListing -i images -o P writes root_path "images": OpenMVG reads it from the
    current directory; a project used from elsewhere falls back to its own folder."""
    names = _project(tmp_path / "P", "images")
    _images((tmp_path if where == "cwd" else tmp_path / "P") / "images", names)
    monkeypatch.chdir(tmp_path)
    assert rotonly("-q", "run", "P/sfm_data.json", "-o", "OUT") == 0
    assert json.loads((tmp_path / "OUT" / "sfm_data.json").read_text())["root_path"] == "images"
    triangulate = json.loads((tmp_path / "OUT" / "reports" / "triangulate.json").read_text())
    assert triangulate["images_missing"] == [] and triangulate["points_coloured"] == triangulate["num_points"] > 0
    expected = "images" if where == "cwd" else "P/images"
    assert triangulate["image_root"] == expected


def test_image_path_is_written_as_root_path(tmp_path, monkeypatch):
    names = _project(tmp_path / "P", "/nowhere")
    _images(tmp_path / "pictures", names)
    monkeypatch.chdir(tmp_path)
    assert rotonly("-q", "run", "P/sfm_data.json", "-o", "OUT", "--image-path", "pictures") == 0
    assert json.loads((tmp_path / "OUT" / "sfm_data.json").read_text())["root_path"] == "pictures"


def test_matches_option_and_input_files_in_the_load_report(tmp_path, monkeypatch):
    _project(tmp_path / "P", "")
    shutil.copyfile(tmp_path / "P" / "matches.e.bin", tmp_path / "P" / "matches.f.bin")
    (tmp_path / "P" / "matches.e.bin").write_bytes(b"\x01")  # unreadable: must not be read with -M
    monkeypatch.chdir(tmp_path)
    assert rotonly("-q", "run", "P/sfm_data.json", "-M", "P/matches.f.bin", "-o", "OUT") == 0
    load = json.loads((tmp_path / "OUT" / "reports" / "load.json").read_text())
    assert load["matches_file"] == "P/matches.f.bin"
    assert load["input_files"][0] == "P/sfm_data.json" and load["input_files"][-1] == "P/matches.f.bin"
    assert sorted(load["input_files"][1:-1]) == [f"P/{k:04d}.feat" for k in range(8)]
    # a bare name is looked up in --matches-dir, as OpenMVG's tools do
    assert rotonly("-q", "run", "P/sfm_data.json", "--matches", "matches.f.bin", "-o", "OUT2") == 0
    assert json.loads((tmp_path / "OUT2" / "reports" / "load.json").read_text())["matches_file"] == "P/matches.f.bin"
    # the default is unchanged: the first of matches.e, matches.f, ... (here the broken one)
    assert rotonly("-q", "run", "P/sfm_data.json", "-o", "OUT3") == 2
    assert rotonly("-q", "run", "P/sfm_data.json", "-M", "P/none.bin", "-o", "OUT3") == 2
    assert not (tmp_path / "OUT3").exists()


def test_database_input_files(tmp_path):
    db = tmp_path / "database.db"
    shutil.copyfile(DATA_FIXTURES / "herzjesu_p8" / "database.db", db)
    assert rotonly("-q", "identify", db, "-o", tmp_path / "OUT") == 0
    load = json.loads((tmp_path / "OUT" / "reports" / "load.json").read_text())
    assert load["input_files"] == [str(db)] and "matches_file" not in load
