"""io.images: which view image names may be read below an image folder."""

from __future__ import annotations

import os

import pytest

from rotonly_cli.io.images import image_file, unsafe_image_name


@pytest.mark.parametrize("name", ["0001.jpg", "sub/0001.JPG", "sub/../0001.png", "./a/b/c.tif", "x..y.jpeg",
                                  "..hidden.png"])
def test_names_inside_the_folder_are_read(name):
    assert unsafe_image_name(name) is None


@pytest.mark.parametrize(("name", "reason"), [
    ("../0001.jpg", "climbs out"), ("sub/../../0001.jpg", "climbs out"), ("..", "climbs out"),
    ("..\\..\\etc\\x.jpg", "climbs out"), ("/etc/passwd", "absolute"), ("/tmp/x.jpg", "absolute"),
    ("C:\\images\\x.jpg", "absolute"), ("\\\\server\\x.jpg", "absolute"), ("passwd", "not an image"),
    ("database.db", "not an image"), ("", "not a file name"), ("a\0b.jpg", "not a file name"),
])
def test_names_leaving_the_folder_or_not_images_are_refused(name, reason):
    assert reason in unsafe_image_name(name)


def test_image_file_reads_regular_files_only(tmp_path):
    (tmp_path / "a.jpg").write_bytes(b"jpeg")
    os.mkfifo(tmp_path / "pipe.jpg")
    (tmp_path / "folder.jpg").mkdir()
    assert image_file(tmp_path, "a.jpg") == (tmp_path / "a.jpg", None)
    assert image_file(tmp_path, "pipe.jpg") == (None, "not a regular file")
    assert image_file(tmp_path, "folder.jpg") == (None, "not a regular file")
    assert image_file(tmp_path, "missing.jpg") == (None, "missing")
    assert image_file(tmp_path, "../a.jpg")[1] == "climbs out of the image folder"
