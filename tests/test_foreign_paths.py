"""Image names that leave the image folder are never read (issue 21): a database whose image
names climb out (``../``), are absolute, are no images or are named pipes still runs (exit 0),
each refused name gets a warning, and no colour comes from a foreign file. With strace (when
installed) the same run is watched: no file outside the input's folder, OUT's folder and the
Python installation is opened, the foreign files not even tried."""

from __future__ import annotations

import os
import re
import shutil
import sqlite3
import subprocess
import sys
import sysconfig
from contextlib import closing
from pathlib import Path

import cv2
import numpy as np
import pytest

import rotonly_cli

from helpers import DATA_FIXTURES

HJ_DB = DATA_FIXTURES / "herzjesu_p8" / "database.db"
RUN = "from rotonly_cli.cli import console_main; console_main()"
BLUE_BGR, RED_BGR = (255, 0, 0), (0, 0, 255)


def hostile_project(tmp_path: Path) -> tuple[Path, Path, dict[int, str]]:
    """project/database.db (the 8-image fixture) with images/ beside it, and a secret/
    folder next to the project holding blue images and a passwd file the names point at."""
    project, secret = tmp_path / "project", tmp_path / "secret"
    (project / "images" / "sub").mkdir(parents=True)
    secret.mkdir()
    for name in ("outside.png", "absolute.png", "deep.png"):
        cv2.imwrite(str(secret / name), np.full((16, 16, 3), BLUE_BGR, np.uint8))
    (secret / "passwd").write_text("root:x:0:0:root:/root:/bin/sh\n")
    (project / "images" / "passwd").write_text("not an image\n")
    os.mkfifo(project / "images" / "pipe.png")
    for name in ("0006.png", "0007.png"):
        cv2.imwrite(str(project / "images" / name), np.full((16, 16, 3), RED_BGR, np.uint8))
    names = {1: "../../secret/outside.png", 2: str(secret / "absolute.png"), 3: "sub/../../../secret/deep.png",
             4: "passwd", 5: "pipe.png", 6: "sub/../0006.png", 7: "0007.png", 8: "0008.png"}
    database = project / "database.db"
    shutil.copyfile(HJ_DB, database)
    with closing(sqlite3.connect(database)) as connection:
        for image_id, name in names.items():
            connection.execute("UPDATE images SET name = ? WHERE image_id = ?", (name, image_id))
        connection.commit()
    return database, secret, names


def run(argv: list, prefix: list | None = None, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """`rotonly` in a subprocess. $USER is set as in any login shell: without it pycolmap's
    logging library looks the user name up in /etc/passwd when it is loaded."""
    return subprocess.run([*(prefix or []), sys.executable, "-c", RUN, *map(str, argv)], capture_output=True,
                          text=True, timeout=600, env={**os.environ, "USER": os.environ.get("USER", "rotonly")},
                          cwd=cwd)


def check_run(result: subprocess.CompletedProcess, out: Path, names: dict[int, str]) -> None:
    import pycolmap

    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    warnings = [line for line in result.stderr.splitlines() if "not read for the point colours" in line]
    assert len(warnings) == 5, result.stderr
    for image_id in (1, 2, 3, 4, 5):
        assert any(repr(names[image_id]) in line for line in warnings), names[image_id]
    colours = np.array([p.color for p in pycolmap.Reconstruction(str(out / "sparse")).points3D.values()])
    assert len(colours) > 1000
    assert not np.any(np.all(colours == BLUE_BGR[::-1], axis=1))  # nothing from the foreign images
    assert np.any(np.all(colours == RED_BGR[::-1], axis=1))  # the images inside the folder are read


def test_names_leaving_the_image_folder_are_not_read(tmp_path):
    database, _, names = hostile_project(tmp_path)
    out = tmp_path / "out"
    check_run(run(["run", database, "-o", out]), out, names)


def _opened_paths(log: Path) -> tuple[set[str], set[str]]:
    """(paths opened, paths tried) of an ``strace -f -e trace=%file`` log."""
    opened, tried = set(), set()
    call = re.compile(r'(?:open|openat|openat2|creat|execve)\((?:AT_FDCWD, |\d+, )?"([^"]*)".*= (-?\d+)')
    for line in log.read_text(errors="replace").splitlines():
        match = call.search(line)
        if match:
            tried.add(match.group(1))
            if int(match.group(2)) >= 0:
                opened.add(match.group(1))
    return opened, tried


@pytest.mark.skipif(shutil.which("strace") is None, reason="strace is not installed (.ci/run installs it)")
def test_no_file_outside_the_input_out_and_python_is_opened(tmp_path):
    database, secret, names = hostile_project(tmp_path)
    out, log = tmp_path / "out", tmp_path / "strace.log"
    result = run(["run", database, "-o", out], ["strace", "-f", "-qq", "-e", "trace=open,openat,openat2,creat",
                                                "-o", str(log)], cwd=database.parent)
    check_run(result, out, names)
    opened, tried = _opened_paths(log)
    assert len(opened) > 50  # the log is real
    assert not [path for path in tried if str(secret) in path or path.endswith("passwd") or "pipe.png" in path]
    runtime = {sys.prefix, sys.base_prefix, sys.exec_prefix, *sysconfig.get_paths().values(),
               str(Path(rotonly_cli.__file__).parent)}
    # the input's folder, OUT and its staging folders, OUT's folder itself (listed for stale
    # staging folders), the interpreter and the packages, the C library's own files
    allowed = (str(database.parent), str(out), str(tmp_path / ".out."), *map(os.path.realpath, runtime), *runtime,
               "/usr/lib/", "/lib/", "/lib64/", "/usr/local/lib/", "/etc/ld.so.", "/etc/localtime",
               "/usr/share/locale/", "/usr/lib/locale/", "/proc/", "/sys/", "/dev/")
    start_up = _interpreter_start_up(tmp_path)
    foreign = sorted(path for path in opened if path != str(tmp_path) and path not in start_up
                     and not os.path.join(str(database.parent), path).startswith(allowed))
    assert not foreign, foreign


def _interpreter_start_up(tmp_path: Path) -> set[str]:
    """The files a bare ``python -c pass`` opens: the machine's own start-up (a ``.pth`` file
    that installs a certificate, say), before any of rotonly's code runs."""
    log = tmp_path / "bare.log"
    subprocess.run(["strace", "-f", "-qq", "-e", "trace=open,openat,openat2,creat", "-o", str(log), sys.executable,
                    "-c", "pass"], check=True, timeout=60)
    return _opened_paths(log)[0]
