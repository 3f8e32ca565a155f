"""`rotonly run --cluster` (issue 50): the per-pair and per-track work on Dask, the same bytes as
`--jobs 1`, a worker killed mid-run, a scheduler that cannot be reached, the extra missing.

One LocalCluster of 2 single-threaded worker processes serves the whole session (dask_host.py,
in a process of its own); each run is a `rotonly` process attached to it by tcp://."""

from __future__ import annotations

import importlib.util
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from helpers import DATA_FIXTURES

DB = DATA_FIXTURES / "colmap38_herzjesu4" / "database.db"
RUN = "from rotonly_cli.cli import console_main; console_main()"
OUTPUTS = ("sfm_data.json", "sparse/cameras.bin", "sparse/images.bin", "sparse/points3D.bin")
#: Dask's packages, absent from a process that ran without --cluster
DASK = ("dask", "distributed")
#: imports of Dask's packages fail, as where the extra is not installed
WITHOUT_DASK = f"""
import sys
class NoDask:
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in {DASK!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
sys.meta_path.insert(0, NoDask())
"""

HAVE_DASK = importlib.util.find_spec("distributed") is not None
needs_dask = pytest.mark.skipif(not HAVE_DASK, reason="needs the extra 'cluster' (dask[distributed])")


def rotonly(*args, prelude: str = "", timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", prelude + RUN, *map(str, args)], capture_output=True, text=True,
                          timeout=timeout)


class DaskHost:
    def __init__(self):
        here = Path(__file__).with_name("dask_host.py")
        self.process = subprocess.Popen([sys.executable, str(here)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                        text=True)
        self.address = self.process.stdout.readline().strip()
        assert self.address.startswith("tcp://"), self.address

    def ask(self, command: str) -> str:
        self.process.stdin.write(command + "\n")
        self.process.stdin.flush()
        return self.process.stdout.readline().strip()

    def close(self) -> None:
        self.process.stdin.close()
        try:
            self.process.wait(timeout=60)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


@pytest.fixture(scope="session")
def dask_cluster():
    host = DaskHost()
    try:
        yield host
    finally:
        host.close()


@pytest.fixture(scope="module")
def serial(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("serial") / "out"
    done = rotonly("-q", "run", DB, "-o", out, "--jobs", 1)
    assert done.returncode == 0, done.stderr
    return out


def assert_same_outputs(a: Path, b: Path) -> None:
    for name in OUTPUTS:
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


@needs_dask
def test_cluster_run_writes_the_bytes_of_jobs_1_and_records_its_tasks(dask_cluster, serial, tmp_path):
    out = tmp_path / "out"
    done = rotonly("run", DB, "-o", out, "--cluster", dask_cluster.address)
    assert done.returncode == 0, done.stderr
    assert_same_outputs(serial, out)
    record = json.loads((out / "reports" / "run.json").read_text())["cluster"]
    assert record["address"] == dask_cluster.address and record["num_workers"] == 2
    stages = record["stages"]
    assert {"load", "identify", "refine", "reject", "triangulate"} <= set(stages)
    for stage in stages.values():
        assert stage["tasks"] >= 1 and stage["bytes_sent"] > 0
        assert sum(stage["tasks_by_worker"].values()) == stage["tasks"]
        assert set(stage["tasks_by_worker"]) <= set(record["workers"])  # ran on the cluster's workers
    assert stages["load"]["bytes_scattered"] > 0  # the keypoints, once
    assert json.loads((out / "reports" / "refine.json").read_text())["processes"] == "cluster"


@needs_dask
def test_a_worker_killed_mid_run_changes_nothing(dask_cluster, serial, tmp_path):
    out = tmp_path / "out"
    run = subprocess.Popen([sys.executable, "-c", RUN, "-q", "run", str(DB), "-o", str(out), "--cluster",
                            dask_cluster.address], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    killed = dask_cluster.ask("kill-busy")
    _, err = run.communicate(timeout=600)
    assert killed.startswith("killed "), killed
    assert run.returncode == 0, err
    assert_same_outputs(serial, out)
    assert dask_cluster.ask("workers") == "2"  # the nanny started another


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@needs_dask
def test_an_unreachable_scheduler_is_exit_2_in_one_line(tmp_path):
    address = f"tcp://127.0.0.1:{free_port()}"
    done = rotonly("run", DB, "-o", tmp_path / "out", "--cluster", address, timeout=120)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and address in lines[0] and lines[0].startswith("error: "), done.stderr
    assert not (tmp_path / "out").exists()


def test_without_the_extra_cluster_is_exit_2_naming_it(tmp_path):
    done = rotonly("run", DB, "-o", tmp_path / "out", "--cluster", "local:2", prelude=WITHOUT_DASK, timeout=120)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "'cluster'" in lines[0] and "rotonly_cli[cluster]" in lines[0], done.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("address", ["local:0", "local:x", "127.0.0.1:8786", "tcp://host", "tcp://:8786"])
def test_a_malformed_address_is_a_usage_error(tmp_path, address):
    done = rotonly("run", DB, "-o", tmp_path / "out", "--cluster", address, prelude=WITHOUT_DASK, timeout=120)
    assert done.returncode == 2 and "--cluster" in done.stderr, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1


def test_the_api_checks_the_address_before_anything_runs():
    from rotonly_cli import run
    from rotonly_cli.errors import InputError

    with pytest.raises(InputError, match="--cluster"):
        run(DB, cluster="somewhere")


def test_a_run_without_cluster_imports_nothing_of_dask(tmp_path):
    check = (f"import sys\nfrom rotonly_cli.cli import main\ntry:\n    main(['-q', 'run', {str(DB)!r}, '-o', "
             f"{str(tmp_path / 'out')!r}])\nexcept SystemExit as exc:\n    assert exc.code == 0, exc.code\n"
             f"print(sorted(m for m in sys.modules if m.partition('.')[0] in {DASK!r}))\n")
    done = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True, timeout=600,
                          env={**os.environ})
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines()[-1] == "[]", done.stdout


class LocalSession:
    """runtime.cluster.ClusterSession's task interface, run in this process in order (no
    Dask): the stages' cluster paths, cut into many small tasks, against their --jobs 1 bytes."""

    def __init__(self):
        from rotonly_cli.runtime.cluster import ClusterSession

        self.stages, self.client, self.tasks, self.address = {}, None, {}, "in this process"
        self.map_edge_chunks = ClusterSession.map_edge_chunks.__get__(self)
        self.record = ClusterSession.record.__get__(self)

    def scatter(self, obj, stage):
        return obj

    def map(self, stage, fn, tasks, total):
        results = [fn(*args) for args in tasks]
        assert len(results) == total
        self.tasks[stage] = self.tasks.get(stage, 0) + total
        return results


def test_many_small_tasks_give_the_bytes_of_one_process(tmp_path, monkeypatch):
    from rotonly_cli import run
    from rotonly_cli.runtime import cluster
    from rotonly_cli.stages import identify, load, refine, reject, triangulate

    db = DATA_FIXTURES / "herzjesu_p8" / "database.db"
    run(db, out=tmp_path / "one", jobs=1)
    for module, name, size in ((load, "CLUSTER_TASK_MATCHES", 3000), (identify, "CLUSTER_TASK_MATCHES", 1),
                               (refine, "CLUSTER_TASK_MATCHES", 1), (reject, "CLUSTER_TASK_MATCHES", 2000),
                               (triangulate, "CLUSTER_TASK_OBSERVATIONS", 1000)):
        monkeypatch.setattr(module, name, size)
    session = LocalSession()
    monkeypatch.setattr(cluster, "_ACTIVE", [session])
    run(db, out=tmp_path / "tasks", jobs=1)
    assert_same_outputs(tmp_path / "one", tmp_path / "tasks")
    assert session.tasks["load"] > 10 and session.tasks["triangulate"] > 10 and session.tasks["reject"] > 1, \
        session.tasks
