"""The per-pair and per-track work of a run on a Dask cluster (``--cluster ADDRESS``, issue 50).

``tcp://HOST:PORT`` attaches to a running scheduler (``dask scheduler``, ``dask worker
tcp://...``); ``local:N`` starts a ``dask.distributed.LocalCluster`` of N single-threaded
worker processes for the run and closes it after. Dask is imported here only when a session
opens: a run without ``--cluster`` never imports it (the extra ``cluster`` is optional).

What travels: the stages cut their work into tasks of consecutive edges (or tracks) sized for
~0.5 s or more each, by the data alone (never by the number of workers), as plain numpy arrays;
the arrays every task of a stage reads (the normalized keypoints) are scattered once
(:meth:`ClusterSession.scatter`). Results come back in task order and are concatenated as the
one-process run concatenates its chunks, so the outputs are the bytes of ``--jobs 1``.
GRRM, the averaging and LiGT stay in this process (the driver).

Faults: a worker that dies has its tasks run again elsewhere (the scheduler does that); a
scheduler that cannot be reached at the start is :class:`ClusterUnavailable` (exit 2, one line
naming the address); a scheduler or every worker lost during the run is :class:`ClusterLost`
(exit 1, one line; OUT stays as it was: io/atomic). Ctrl-C closes the session (the local
cluster's worker processes with it) as it unwinds.
"""

from __future__ import annotations

import logging
import signal
import statistics
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager, nullcontext

from rotonly_cli.errors import AlgorithmError, InputError
from rotonly_cli.options.common import cluster_address
from rotonly_cli.runtime import heartbeat

logger = logging.getLogger(__name__)

#: the optional extra that brings Dask (pyproject.toml)
EXTRA = "cluster"
#: seconds to reach a tcp:// scheduler at the start (short: a wrong address fails fast)
CONNECT_TIMEOUT_S = 5.0
#: seconds a tcp:// scheduler may take to have a worker at the start
WORKER_TIMEOUT_S = 30.0
#: seconds without a scheduler or without any worker during a run before it is given up
LOST_AFTER_S = 30.0
#: seconds between two looks at the cluster's health while tasks run
POLL_S = 0.5
#: tasks in flight per worker (more are built as results come back: the driver holds the
#: arrays of these only, not of the whole stage)
TASKS_IN_FLIGHT_PER_WORKER = 2

#: imported by each local worker as it starts: it leaves Ctrl-C to this process
WORKER_PRELOAD = "rotonly_cli.runtime.cluster_worker"

_ACTIVE: list[ClusterSession] = []


class ClusterUnavailable(InputError):
    """No cluster to run on at the start (exit 2): the extra is missing, or the scheduler
    cannot be reached or has no worker."""


class ClusterLost(AlgorithmError):
    """The cluster went away during the run (exit 1): the scheduler, or every worker."""


def active() -> ClusterSession | None:
    """The session the run in progress sends its tasks to, None without --cluster."""
    return _ACTIVE[-1] if _ACTIVE else None


def map_edges(stage: str, fn: Callable, R, counts, jobs: int, arrays_of: Callable, build_batch: Callable, shared,
              batch_of: Callable, task_matches: int):
    """(``fn(R, batch)`` over every edge, where it ran) for a per-edge stage: on the --cluster
    session in tasks of ``task_matches`` matches (:meth:`ClusterSession.map_edge_chunks` with
    ``arrays_of``, ``build_batch``, ``shared``), else over ``jobs`` forked processes, chunk by
    chunk (runtime.parallel.map_edge_chunks with ``batch_of(e0, e1)``); where it ran: "cluster"
    or the number of processes."""
    import numpy as np

    from rotonly_cli.runtime.parallel import map_edge_chunks, plan_counts

    session = active()
    if session is not None:
        return session.map_edge_chunks(stage, fn, R, counts, arrays_of, build_batch, shared, task_matches), "cluster"
    ranges = plan_counts(counts, jobs)
    with np.errstate(all="ignore"):  # handled corner cases (rotonly_cli.twoview._quiet)
        # chunk by chunk: the matches of one chunk of edges at a time (issue 49)
        return map_edge_chunks(fn, R, counts, batch_of, ranges), len(ranges)


def owns_thread(thread) -> bool:
    """Whether ``thread`` is one of Dask's (a session is open and it is a daemon thread that
    was not alive before the session opened): runtime.parallel forks beside those, since the
    forked children never touch the cluster. rotonly's own threads are never daemons."""
    session = active()
    return session is not None and thread.daemon and thread.ident not in session.threads_before


def _register_owns_thread() -> None:
    from rotonly_cli.runtime import parallel

    if owns_thread not in parallel.FORK_SAFE_THREADS:
        parallel.FORK_SAFE_THREADS.append(owns_thread)


_register_owns_thread()


def session_for(address: str | None, progress: bool = False):
    """A context manager: the :class:`ClusterSession` of ``address`` (None: no session, and
    nothing of Dask imported)."""
    return nullcontext(None) if address is None else ClusterSession(address, progress)


@contextmanager
def _sigint_deferred() -> Iterator[None]:
    """Ctrl-C while the cluster starts answered once it has started (then closed again as
    the run unwinds): a start interrupted half-way could leave worker processes behind."""
    caught = []
    try:
        previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught:
            raise KeyboardInterrupt


#: loggers of the libraries under Dask's client: silent unless -vv (their errors, such as a
#: reconnection's traceback, come back to rotonly as ClusterLost, one line)
DASK_LOGGERS = ("distributed", "tornado", "asyncio")


def _quiet_dask() -> None:
    if logging.getLogger().getEffectiveLevel() <= logging.DEBUG:
        return
    for name in list(logging.root.manager.loggerDict):
        if name.partition(".")[0] in DASK_LOGGERS:
            logging.getLogger(name).setLevel(logging.CRITICAL + 1)
    for name in DASK_LOGGERS:
        logging.getLogger(name).setLevel(logging.CRITICAL + 1)


def _import_dask():
    try:
        import distributed
    except ImportError as exc:
        raise ClusterUnavailable(f"needs Dask, the optional extra {EXTRA!r}: pip install 'rotonly_cli[{EXTRA}]' "
                                 f"({exc})", field="--cluster") from None
    return distributed


def code_fingerprint() -> str:
    """The version and a digest of rotonly_cli's sources here: a worker must run the same code
    (same functions, same numbers)."""
    import hashlib
    from importlib.metadata import PackageNotFoundError, version
    from pathlib import Path

    package = Path(__file__).resolve().parents[1]
    digest = hashlib.sha1()
    for path in sorted(package.rglob("*.py")):
        digest.update(path.relative_to(package).as_posix().encode() + b"\0" + path.read_bytes())
    try:
        release = version("rotonly_cli")
    except PackageNotFoundError:
        release = "?"
    return f"{release}+{digest.hexdigest()[:12]}"


def _run_task(fn: Callable, *args):
    """On a worker: (this worker's address, seconds, ``fn(*args)``)."""
    from distributed import get_worker

    start = time.perf_counter()
    value = fn(*args)
    return get_worker().address, time.perf_counter() - start, value


def group_ranges(ranges: list[tuple[int, int]], counts, at_least: int) -> list[list[tuple[int, int]]]:
    """Consecutive ``ranges`` (of items with ``counts``) grouped until each group holds
    ``at_least`` (the last may hold less): a cluster task's share, fixed by the data alone."""
    groups, group, size = [], [], 0
    for a, b in ranges:
        group.append((a, b))
        size += int(counts[a:b].sum())
        if size >= at_least:
            groups.append(group)
            group, size = [], 0
    if group:
        groups.append(group)
    return groups


def _edge_chunks_task(fn: Callable, build_batch: Callable, shared, R, arrays, chunks: list[tuple[int, int]]):
    """On a worker: ``fn`` on each chunk's batch in turn, concatenated (as runtime.parallel's
    one process does)."""
    import numpy as np

    from rotonly_cli.runtime.parallel import concat_results

    with np.errstate(all="ignore"):  # the stages' handled corner cases (rotonly_cli.twoview._quiet)
        parts = [fn(R[c0:c1], build_batch(shared, arrays, c0, c1)) for c0, c1 in chunks]
    return parts[0] if len(parts) == 1 else concat_results(parts)


def _nbytes(value) -> int:
    """Bytes of the arrays in ``value`` (tuples, lists, dicts and dataclasses of arrays)."""
    import dataclasses

    import numpy as np

    if isinstance(value, np.ndarray):
        return int(value.nbytes)
    if isinstance(value, list | tuple):
        return sum(_nbytes(v) for v in value)
    if isinstance(value, dict):
        return sum(_nbytes(v) for v in value.values())
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return sum(_nbytes(getattr(value, f.name)) for f in dataclasses.fields(value))
    return 0


class ClusterSession:
    """A Dask client for the run (and the local cluster of ``local:N``): ``with`` opens and
    closes it; :meth:`map` runs a stage's tasks. Counts per stage what went where
    (:meth:`record`, for reports/run.json)."""

    def __init__(self, address: str, progress: bool = False):
        self.kind, self.target = cluster_address(address)
        self.address = address
        self.progress = progress
        self.client = None
        self._cluster = None
        self._scattered: dict[int, tuple[object, object]] = {}  # id(obj) -> (obj, its future)
        self._token = uuid.uuid4().hex[:8]
        self.stages: dict[str, dict] = {}
        self.threads_before: set[int] = set()

    # ------------------------------------------------------------------ open / close
    def __enter__(self) -> ClusterSession:
        import threading

        self.threads_before = {t.ident for t in threading.enumerate()}
        distributed = _import_dask()
        try:
            with _sigint_deferred():
                self._connect(distributed)
        except BaseException:
            self.close()
            raise
        _ACTIVE.append(self)
        return self

    def _connect(self, distributed) -> None:
        _quiet_dask()
        if self.kind == "local":
            self._cluster = distributed.LocalCluster(n_workers=self.target, threads_per_worker=1, processes=True,
                                                     dashboard_address=":0", host="127.0.0.1",
                                                     silence_logs=logging.CRITICAL, preload=[WORKER_PRELOAD])
            _quiet_dask()  # the scheduler runs here: its loggers too
            self.client = distributed.Client(self._cluster, set_as_default=True)
            self.address = f"local:{self.target}"
            self.scheduler = self._cluster.scheduler_address
        else:
            try:
                self.client = distributed.Client(self.target, timeout=CONNECT_TIMEOUT_S, set_as_default=True)
            except (OSError, TimeoutError) as exc:
                raise ClusterUnavailable(f"cannot reach a Dask scheduler at {self.target} ({exc})",
                                         field="--cluster") from None
            self.scheduler = self.target
            try:
                self.client.wait_for_workers(1, timeout=WORKER_TIMEOUT_S)
            except (OSError, TimeoutError):
                raise ClusterUnavailable(f"the Dask scheduler at {self.target} has no worker after "
                                         f"{WORKER_TIMEOUT_S:.0f} s", field="--cluster") from None
        self._check_code(distributed)
        logger.info("cluster: %s (scheduler %s), %d worker(s)", self.address, self.scheduler, self.num_workers())

    def _check_code(self, distributed) -> None:
        """ClusterUnavailable unless the scheduler can read rotonly's tasks and every worker
        runs this rotonly_cli (code_fingerprint)."""
        here = code_fingerprint()
        try:
            theirs = self.client.submit(code_fingerprint, pure=False).result(timeout=WORKER_TIMEOUT_S)
            workers = set(self.client.run(code_fingerprint).values())
        except Exception as exc:  # noqa: BLE001 - a scheduler or worker that cannot load rotonly_cli
            first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
            raise ClusterUnavailable(f"the Dask cluster at {self.target} cannot run rotonly's tasks ({first}): "
                                     f"its scheduler and workers need this rotonly_cli installed", field="--cluster") \
                from None
        if workers | {theirs} != {here}:
            raise ClusterUnavailable(f"the workers of the Dask cluster at {self.target} run another rotonly_cli "
                                     f"({', '.join(sorted(workers | {theirs}))}; here {here})", field="--cluster")

    def close(self) -> None:
        """Close the client and a local cluster (its worker processes end with it)."""
        self._scattered.clear()
        client, cluster, self.client, self._cluster = self.client, self._cluster, None, None
        for thing in (client, cluster):
            if thing is None:
                continue
            try:
                thing.close(timeout=10) if thing is client else thing.close()
            except Exception as exc:  # noqa: BLE001 - closing what may be gone already
                logger.debug("cluster: closing %s: %s", type(thing).__name__, exc)

    def __exit__(self, *exc) -> None:
        if _ACTIVE and _ACTIVE[-1] is self:
            _ACTIVE.pop()
        self.close()

    # ------------------------------------------------------------------ health
    def num_workers(self) -> int:
        info = self.client.scheduler_info()
        return int(info.get("n_workers", len(info.get("workers", {}))))

    def _lost(self, exc: BaseException | None = None) -> ClusterLost:
        """The one-line error of a cluster lost during the run (``exc``: what said so)."""
        if exc is None:
            reason = f"no scheduler or no worker for {LOST_AFTER_S:.0f} s"
        else:
            first = (str(exc).strip().splitlines() or [""])[0]
            reason = f"{type(exc).__name__}: {first}" if first else type(exc).__name__
        return ClusterLost(f"the Dask cluster at {self.address} was lost during the run ({reason})")

    def _healthy(self) -> bool:
        if self.client is None or self.client.status != "running":
            return False
        try:
            return self.num_workers() > 0
        except Exception:  # noqa: BLE001 - the scheduler went away during the call
            return False

    # ------------------------------------------------------------------ work
    def scatter(self, obj, stage: str):
        """A future of ``obj`` on the cluster, sent once per object and replicated on the
        workers (kept until the session closes; ``obj`` must not change meanwhile: the stages
        scatter read-only inputs). Its bytes (sent from here once) count as ``stage``'s."""
        key = id(obj)
        if key not in self._scattered:
            [future] = self.client.scatter([obj], hash=False)
            # a copy on every worker, passed on among them (a tree, not n sends from here): the
            # death of a worker loses no scattered data, which the scheduler could not remake
            self.client.replicate([future])
            self._scattered[key] = (obj, future)
            self._stage(stage)["bytes_scattered"] += _nbytes(obj)
        return self._scattered[key][1]

    def _stage(self, stage: str) -> dict:
        return self.stages.setdefault(stage, {"tasks": 0, "bytes_sent": 0, "bytes_scattered": 0,
                                              "bytes_received": 0, "time_s": 0.0, "task_s": [], "tasks_by_worker": {}})

    def map(self, stage: str, fn: Callable, tasks: Iterable[tuple], total: int) -> list:
        """``[fn(*args) for args in tasks]`` on the cluster, in the order of ``tasks`` (a
        generator: the arguments of a few tasks per worker exist at a time). ``fn`` must be
        importable by the workers (a module-level function). An exception ``fn`` raises is
        raised here; a cluster lost meanwhile is :class:`ClusterLost`."""
        from distributed import wait

        record = self._stage(stage)
        start = time.perf_counter()
        results: dict[int, object] = {}
        pending: dict[object, int] = {}
        source = iter(tasks)
        submitted = 0
        window = max(4, TASKS_IN_FLIGHT_PER_WORKER * self.num_workers())
        with self._progress(stage, total) as advance:
            while True:
                while len(pending) < window:
                    args = next(source, None)
                    if args is None:
                        break
                    record["bytes_sent"] += _nbytes(args)
                    future = self.client.submit(_run_task, fn, *args, pure=False,
                                                key=f"rotonly-{stage}-{self._token}-{submitted}")
                    pending[future] = submitted
                    submitted += 1
                if not pending:
                    break
                for future in self._finished(wait, pending):
                    index = pending.pop(future)
                    worker, seconds, value = self._result(future)
                    results[index] = value
                    record["bytes_received"] += _nbytes(value)
                    record["task_s"].append(seconds)
                    record["tasks_by_worker"][worker] = record["tasks_by_worker"].get(worker, 0) + 1
                    future.release()
                    advance()
        record["tasks"] += submitted
        record["time_s"] += time.perf_counter() - start
        return [results[i] for i in range(submitted)]

    def map_edge_chunks(self, stage: str, fn: Callable, R, counts, arrays_of: Callable, build_batch: Callable,
                        shared, task_matches: int, chunk: int | None = None):
        """runtime.parallel.map_edge_chunks on the cluster: ``fn(R, batch)`` (a per-edge
        dataclass result) over every edge, in the chunks of ``--jobs 1`` (chunk_ranges of
        ``chunk`` matches, STAGE_CHUNK_MATCHES by default), consecutive chunks grouped into
        tasks of ``task_matches`` matches or more (the data decides, not the workers).
        ``arrays_of(e0, e1)``: the plain arrays of edges [e0, e1), made here as the tasks go
        out; ``build_batch(shared, arrays, c0, c1)``, on the worker: the batch of edges
        [c0, c1) of a task; ``shared``: what every task reads (scattered once)."""
        import numpy as np

        from rotonly_cli.runtime.parallel import STAGE_CHUNK_MATCHES, chunk_ranges, concat_results

        counts = np.asarray(counts, dtype=np.int64)
        chunks = chunk_ranges(counts, 0, len(counts), STAGE_CHUNK_MATCHES if chunk is None else chunk)
        groups = group_ranges(chunks, counts, task_matches)
        reference = self.scatter(shared, stage)

        def tasks():
            for group in groups:
                a, b = group[0][0], group[-1][1]
                yield (fn, build_batch, reference, R[a:b], arrays_of(a, b), [(c0 - a, c1 - a) for c0, c1 in group])

        parts = self.map(stage, _edge_chunks_task, tasks(), len(groups))
        return parts[0] if len(parts) == 1 else concat_results(parts)

    def _finished(self, wait, pending: dict) -> list:
        """The futures of ``pending`` done by now (waiting for one at least), watching the
        cluster's health meanwhile."""
        unhealthy_since = None
        while True:
            try:
                done = wait(list(pending), timeout=POLL_S, return_when="FIRST_COMPLETED").done
            except TimeoutError:
                done = ()
            except Exception as exc:  # noqa: BLE001 - the client's connection broke
                raise self._lost(exc) from None
            if done:
                return [future for future in pending if future in done]
            if self._healthy():
                unhealthy_since = None
            elif unhealthy_since is None:
                unhealthy_since = time.monotonic()
            elif time.monotonic() - unhealthy_since > LOST_AFTER_S:
                raise self._lost()

    def _result(self, future):
        from concurrent.futures import CancelledError

        from distributed import KilledWorker

        try:
            return future.result()
        except (KilledWorker, CancelledError) as exc:
            raise self._lost(exc) from None
        except OSError as exc:  # CommClosedError and other broken connections
            if type(exc).__module__.startswith("distributed"):
                raise self._lost(exc) from None
            raise

    @contextmanager
    def _progress(self, stage: str, total: int) -> Iterator[Callable[[], None]]:
        """Tasks done / total: a bar on a terminal, else counted for the progress lines."""
        if self.progress:
            from rotonly_cli.runtime.progress import progress_bar

            with progress_bar(total=total, desc=f"{stage} (cluster)", unit="task", leave=False) as bar:
                yield lambda: bar.update(1)
            return
        with heartbeat.task("cluster tasks", total) as advance:
            yield advance

    def record(self) -> dict:
        """For reports/run.json: the address, the workers, and per stage the tasks, the bytes
        sent (task arguments; scattered arrays apart), received, and the task times."""
        stages = {}
        for stage, record in self.stages.items():
            times = record["task_s"]
            stages[stage] = {**{k: v for k, v in record.items() if k != "task_s"},
                             "task_s": {"min": min(times), "median": statistics.median(times), "max": max(times)}
                             if times else None}
        workers = None
        try:
            workers = sorted(self.client.scheduler_info().get("workers", {})) if self.client is not None else None
        except Exception:  # noqa: BLE001 - a record of a cluster already lost
            pass
        return {"address": self.address, "scheduler": getattr(self, "scheduler", None), "workers": workers,
                "num_workers": None if workers is None else len(workers), "stages": stages}
