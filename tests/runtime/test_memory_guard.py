"""The memory guard (runtime/memory.py) and the progress lines of a pipe (runtime/heartbeat.py):
a stage predicted above --max-memory, or running out of memory, ends the run with exit 1, one
error line and OUT as it was; in a pipe, timestamped progress lines."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rotonly_cli import chain
from rotonly_cli.cli import main
from rotonly_cli.errors import InputError, OutOfMemoryError
from rotonly_cli.options import RunOptions
from rotonly_cli.runtime import heartbeat, memory
from rotonly_cli.scene.types import View
from rotonly_cli.scene.view_graph import Edge, ViewGraph

from helpers import DATA_FIXTURES, REPOSITORY, folder_bytes

DATABASE = DATA_FIXTURES / "colmap38_herzjesu4" / "database.db"  # 4 views, 26 225 stored matches


def _rotonly(capsys, *args) -> tuple[int, list[str]]:
    with pytest.raises(SystemExit) as exit_info:
        main([str(a) for a in args])
    return exit_info.value.code, capsys.readouterr().err.splitlines()


@pytest.fixture
def previous_out(tmp_path) -> Path:
    """An earlier workspace OUT with sentinel files (replaceable: only workspace names at the top)."""
    out = tmp_path / "out"
    (out / "reports").mkdir(parents=True)
    (out / "run.log").write_bytes(b"sentinel run.log\n")
    (out / "reports" / "sentinel.json").write_bytes(b'{"sentinel": 1}\n')
    return out


def _siblings(out: Path) -> list[str]:
    return sorted(p.name for p in out.parent.iterdir())


def test_max_memory_below_the_load_prediction_stops_before_loading(capsys, previous_out):
    before, siblings = folder_bytes(previous_out), _siblings(previous_out)
    code, err = _rotonly(capsys, "-q", "run", DATABASE, "-o", previous_out, "--max-memory", "0.05")
    assert code == 1
    assert len(err) == 1
    # 26 225 stored matches, 48 403 keypoints: 160 MiB + 34 B x 26 225 + 48 B x 48 403 = 0.159 GiB
    assert err[0] == ("error: load needs about 0.16 GB (26225 matches, 48403 keypoints, 4 views, 6 edges), above the "
                      "limit of 0.05 GB (--max-memory)"), err[0]
    assert folder_bytes(previous_out) == before
    assert _siblings(previous_out) == siblings  # no staging folder left beside OUT


def test_max_memory_between_stages_stops_at_the_first_stage_above_it(capsys, previous_out, monkeypatch):
    # LiGT's chunk term (2000 B x min(50 000, 15 818 observations)) puts translate at 0.191 GiB, the stages
    # before it at 0.160-0.165: 0.17 lets load .. optimize run and stops before translate when no smaller
    # chunk may be taken
    monkeypatch.setattr(memory, "MIN_CHUNK", 50_000)
    before = folder_bytes(previous_out)
    code, err = _rotonly(capsys, "run", DATABASE, "-o", previous_out, "--max-memory", "0.17")
    assert code == 1
    errors = [line for line in err if "error" in line or "Traceback" in line]
    assert errors == ["error: translate needs about 0.19 GB (12071 matches, 15818 observations, 4 views, 6 edges, "
                      "10527 pairs within observations), above the limit of 0.17 GB (--max-memory)"], err
    assert any("optimize (GRRM): 4 views, 6 edges" in line for line in err), err  # the stages before it ran
    assert folder_bytes(previous_out) == before


def test_max_memory_degrades_ligt_to_smaller_chunks(capsys, tmp_path):
    import json

    out = tmp_path / "out"
    code, err = _rotonly(capsys, "run", DATABASE, "-o", out, "--max-memory", "0.17")
    assert code == 0, err
    record = json.loads((out / "reports" / "run.json").read_text())["memory"]
    chunks = {entry["stage"]: entry.get("chunk_size") for entry in record["stages"]}
    # 0.1615 GiB besides the chunk leaves 9.1 MB: 2000 B x 4563 constraints; 50 000 halved to 3125
    assert chunks == {"load": None, "identify": None, "refine": None, "average": None, "optimize": None,
                      "translate": 3125, "reject": 3125, "triangulate": None, "export": None}
    assert all(entry["predicted_gb"] <= 0.17 for entry in record["stages"])
    assert any("LiGT in chunks of 3125 constraints to fit in 0.17 GB" in line for line in err), err


def test_memory_error_in_a_stage_is_one_line(capsys, previous_out, monkeypatch):
    def allocate(run):
        np.empty(1 << 46, dtype=np.uint8)  # 64 TiB: numpy's _ArrayMemoryError

    monkeypatch.setitem(chain.STAGE_FUNCTIONS, "optimize", allocate)
    before = folder_bytes(previous_out)
    code, err = _rotonly(capsys, "-q", "run", DATABASE, "-o", previous_out)
    assert code == 1
    assert len(err) == 1
    assert re.fullmatch(r"error: optimize ran out of memory \(Unable to allocate 64\.0 TiB for an array with shape "
                        r"\(70368744177664,\) and data type uint8\); it needs about 0\.16 GB \(12071 matches, .*\)",
                        err[0]), err[0]
    assert folder_bytes(previous_out) == before


@pytest.mark.parametrize("value", ["0", "-1", "nan"])
def test_non_positive_max_memory_is_a_usage_error(capsys, tmp_path, value):
    code, err = _rotonly(capsys, "run", DATABASE, "-o", tmp_path / "out", "--max-memory", value)
    assert code == 2
    assert len(err) == 1 and err[0].startswith("error: rotonly run: Invalid value for '--max-memory'"), err
    assert not (tmp_path / "out").exists()


def test_api_max_memory_maps_to_the_option(tmp_path):
    from rotonly_cli import api

    with pytest.raises(OutOfMemoryError, match=r"^load needs about 0\.16 GB .* \(--max-memory\)$"):
        api.run(DATABASE, max_memory=0.05)
    with pytest.raises(InputError, match="max_memory"):
        api.run(DATABASE, max_memory=-1.0)


def test_run_json_records_predictions_and_limit(capsys, tmp_path):
    import json

    out = tmp_path / "out"
    code, _ = _rotonly(capsys, "-q", "run", DATABASE, "-o", out, "--max-memory", "100")
    assert code == 0
    record = json.loads((out / "reports" / "run.json").read_text())["memory"]
    assert record["max_memory_gb"] == 100.0
    assert record["limit_source"] in ("--max-memory", "available memory")
    stages = [entry["stage"] for entry in record["stages"]]
    assert stages == ["load", "identify", "refine", "average", "optimize", "translate", "reject", "triangulate",
                      "export"]
    optimize = record["stages"][4]
    assert optimize["counts"]["matches"] == 12071 and optimize["counts"]["pairs"] == 10527
    assert not (out / "reports" / "memory.json").exists()


def test_graph_counts_pairs_within_observations():
    # keypoint 0 of view 1 is matched to views 0, 2 and 3: one observation in 3 matches -> 3 pairs
    graph = ViewGraph(views={v: View(v, f"{v}.jpg", 0) for v in range(4)})
    for i, j, matches in ((0, 1, [[0, 0], [1, 1]]), (1, 2, [[0, 0]]), (1, 3, [[0, 5]])):
        graph.edges.append(Edge(i, j, np.eye(3), np.zeros(3), np.array(matches)))
    normalized = {v: np.zeros((6, 3)) for v in range(4)}
    counts = memory.graph_counts(graph, normalized)
    # observations: (0,0) (0,1) (1,0) (1,1) (2,0) (3,5); (1,0) in 3 matches, the others in 1
    assert counts == memory.Counts(matches=4, observations=6, keypoints=24, views=4, edges=3, pairs=3)


def test_every_stage_has_a_footprint():
    assert set(memory.STAGE_FOOTPRINTS) == set(chain.STAGES) | {"export"}


def test_ligt_chunks_shrink_to_fit():
    counts = memory.Counts(matches=1_000_000, observations=500_000)
    footprint = memory.STAGE_FOOTPRINTS["translate"]
    full = footprint.bytes(counts, 50_000)
    guard = memory.MemoryGuard(max_memory_gb=(full - 30_000 * footprint.per_chunk_row) / memory.GB)
    options = guard.check("translate", counts, RunOptions())
    assert options.translate.chunk_size == 12_500  # 50 000 halved until the prediction fits
    assert guard.predictions[-1].bytes <= guard.limit.bytes


def test_limit_is_the_smaller_of_the_option_and_the_available_memory():
    available = memory.available_bytes()
    assert available is not None and available > memory.rss_bytes()
    assert memory.Limit.in_force(0.001) == memory.Limit(0.001 * memory.GB, "--max-memory")
    assert memory.Limit.in_force(1e6).source == "available memory"


LINE = re.compile(r"\d\d:\d\d:\d\d \S+: (\d+/\d+ \(\d+%\) ETA (\d\d:\d\d|--:--)|running for \d\d:\d\d)")


def test_progress_lines_in_a_pipe(tmp_path):
    script = ("import sys; from rotonly_cli.runtime import heartbeat; heartbeat.INTERVAL_S = 0.02; "
              "from rotonly_cli.cli import console_main; sys.argv = ['rotonly'] + sys.argv[1:]; console_main()")
    completed = subprocess.run([sys.executable, "-c", script, "run", str(DATABASE), "-o", str(tmp_path / "out")],
                               capture_output=True, text=True, timeout=60,
                               cwd=REPOSITORY, env={"PYTHONPATH": str(REPOSITORY), "PATH": "/usr/bin:/bin"})
    assert completed.returncode == 0, completed.stderr[-2000:]
    lines = [line for line in completed.stderr.splitlines() if LINE.fullmatch(line)]
    assert len(lines) >= 5, completed.stderr[-2000:]
    counted = [line for line in lines if "optimize/GRRM: " in line and "ETA" in line]
    assert counted, lines


def test_progress_line_format():
    with heartbeat.task("reject", 5) as advance:
        advance(2)
        line = heartbeat.progress_line(now=heartbeat._TASKS[-1].started + 30.0)
    assert re.fullmatch(r"\d\d:\d\d:\d\d reject: 2/5 \(40%\) ETA 00:45", line), line
    assert heartbeat.progress_line() is None


def test_address_space_limit_lowers_the_available_memory(monkeypatch):
    import resource

    mapped = memory._status_kb("VmSize") * 1024
    monkeypatch.setattr(resource, "getrlimit", lambda which: (mapped + 100 * 1024 * 1024, resource.RLIM_INFINITY))
    expected = memory.rss_bytes() + 100 * 1024 * 1024
    assert abs(memory.available_bytes() - expected) < 20 * 1024 * 1024


def test_address_space_cap_in_a_child_is_one_line(tmp_path, previous_out):
    """`prlimit --as` below the run's need (issue 53): exit 1, one error line, OUT as it was."""
    # room for the start (BLAS buffers, threads: memory.START_ROOM) and 10 MiB more; the load stage's
    # base raised to 1 GiB, so that its prediction meets the limit the address space leaves
    script = ("import resource, sys; import numpy, scipy.sparse.linalg, pycolmap; import rotonly_cli.pipeline; "
              "from rotonly_cli.runtime import memory; "
              "memory.STAGE_FOOTPRINTS['load'] = memory.Footprint(memory.GB, per_match=34.0, per_keypoint=48.0); "
              "cap = memory._status_kb('VmSize') * 1024 + int(memory.START_ROOM) + 10 * 1024 * 1024; "
              "resource.setrlimit(resource.RLIMIT_AS, (cap, cap)); "
              "from rotonly_cli.cli import main; main(sys.argv[1:])")
    before = folder_bytes(previous_out)
    completed = subprocess.run([sys.executable, "-c", script, "-q", "run", str(DATABASE), "-o", str(previous_out)],
                               capture_output=True, text=True, timeout=60, cwd=REPOSITORY,
                               env={"PYTHONPATH": str(REPOSITORY), "PATH": "/usr/bin:/bin"})
    assert completed.returncode == 1, completed.stderr[-2000:]
    lines = completed.stderr.splitlines()
    assert len(lines) == 1 and re.fullmatch(r"error: load needs about 1\.0\d GB \(26225 matches, .*\), above the limit "
                                            r"of 0\.[1-3]\d GB \(available memory\)", lines[0]), lines
    assert folder_bytes(previous_out) == before
