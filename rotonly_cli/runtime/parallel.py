"""Edge-parallel TRRM and scene identification over forked processes, and the forked helpers
of GRRM, LiGT's robust rounds and the export (:class:`ForkedPeer`, :class:`ForkedCall`).

Every per-edge quantity of the two-view core (geometry/trrm.py, geometry/identification.py) depends
on that edge's matches only, so the edges can be cut into contiguous parts that are refined
side by side. Threads do not pay: the lean kernels issue many small numpy calls per group of
edges and hold the GIL between them (two threads on edge halves: 1.16-1.6x on 2 cores,
scripts/bench/throughput.py), while two processes reach 1.8x. The parts go to forked
children (they inherit the match arrays; only the small per-edge results come back through
a pipe) and the first part runs in this process. The stages build each part's matches chunk
by chunk (:func:`map_edge_chunks`), so their memory is that of one chunk, not of every match.

Forking is only used where it is safe and pays: on Linux, when this process runs no other
Python thread (a fork copies only the calling thread; the point colours are decoded by a
forked child for that reason) but the Dask client's of a ``--cluster`` run, and with at
least ``MIN_MATCHES_PER_JOB`` matches per part.
Otherwise the same code runs serially, so ``jobs`` never changes the numbers beyond the last
bits (per-edge results are the same functions of the same data). A child that dies without
its result (killed, out of memory) costs time, not the run: this process computes its part,
after a warning.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import mmap
import multiprocessing as mp
import os
import signal
import sys
import threading
from collections.abc import Callable, Sequence

import numpy as np

#: fewest matches per part: a fork costs ~10-30 ms (page tables of a large process) and a
#: pass of the lean kernels ~0.15 us per match, but a part runs a whole stage (TRRM: its LM
#: iterations, ~4 us per match in all), so 2 x 20 000 matches already pay: refine 0.31 ->
#: 0.20 s on Herz-Jesus-P8's database (41 000 matches), 0.31 -> 0.22 s on entry-P10's (74 000)
MIN_MATCHES_PER_JOB = 20_000


#: seconds a child that sent its result may take to exit before it is terminated
DELIVERED_EXIT_TIMEOUT_S = 10.0

logger = logging.getLogger(__name__)


class WorkerDied(RuntimeError):
    """A forked child ended without sending its result (killed, out of memory, os._exit)."""

    def __init__(self, exitcode: int | None):
        super().__init__(f"worker process died (exit code {exitcode})")
        self.exitcode = exitcode


def _receive_or_take_over(conn, process, what: str, take_over: Callable[[], object]):
    """The value a child sent (:func:`_receive_outcome`); should the child have died without
    one, ``take_over()`` computed here, after a warning naming the ``what`` that died."""
    try:
        return _receive_outcome(conn, process)
    except WorkerDied as exc:
        logger.warning("a %s died (exit code %s): its work is done in this process", what, exc.exitcode)
        return take_over()


def _start_child(ctx, fn: Callable, item):
    """A forked child sending ``fn(item)``'s outcome (:func:`_send_outcome`): (process, the
    read end of its pipe, which reaches EOF when the child dies)."""
    receive, send = ctx.Pipe(duplex=False)
    process = ctx.Process(target=_child, args=(send, fn, item), daemon=True)
    process.start()
    send.close()  # the child holds the write end
    return process, receive


def _reap(process, conn, delivered: bool = True) -> None:
    """Close this end of the child's pipe and end the child: one that delivered its result
    exits by itself (SIGTERM would race its exit; pycolmap's failure handler then prints a
    stack trace), the others are stopped."""
    conn.close()
    if delivered:
        process.join(timeout=DELIVERED_EXIT_TIMEOUT_S)
    if process.is_alive():
        process.terminate()
    process.join()


def usable_cpus() -> int:
    """CPUs this process may run on (the affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def fork_safe() -> bool:
    """Whether forking this process is safe: Linux, no other Python thread alive (a fork
    copies only the calling thread; locks held by the others would stay locked in the child),
    and not a daemonic multiprocessing worker (those may not start children)."""
    return sys.platform.startswith("linux") and "fork" in mp.get_all_start_methods() \
        and _no_other_threads() and not mp.current_process().daemon


def _no_other_threads() -> bool:
    """No Python thread alive but this one, or only the Dask client's of a ``--cluster`` run
    (runtime/cluster.owns_thread): those run its event loop and never touch what a forked
    child does (a child answers from its own copy of the memory and exits with os._exit)."""
    others = [t for t in threading.enumerate() if t is not threading.current_thread()]
    if not others:
        return True
    if "rotonly_cli.runtime.cluster" not in sys.modules:  # no session was ever opened
        return False
    from rotonly_cli.runtime.cluster import owns_thread

    return all(owns_thread(t) for t in others)


def would_fork(num_matches: int, jobs: int) -> bool:
    """Whether :func:`plan` would give ``num_matches`` matches more than one process, were
    no other thread running: ``jobs`` > 1 on Linux, and at least two parts of
    ``MIN_MATCHES_PER_JOB`` matches."""
    return (jobs > 1 and sys.platform.startswith("linux") and "fork" in mp.get_all_start_methods()
            and num_matches // MIN_MATCHES_PER_JOB >= 2)


def helper_class(num_matches: int, jobs: int, min_total: int = 0):
    """:class:`ForkedPeer` where a helper process for half of each evaluation pays and is
    safe (:func:`would_fork`, :func:`fork_safe`, and at least ``min_total`` matches or
    observations: where the caller measured it to pay), else None: the ``peer_class`` GRRM and
    the robust LiGT take (their numbers do not depend on it)."""
    return ForkedPeer if num_matches >= min_total and would_fork(num_matches, jobs) and fork_safe() else None


def edge_parts(counts: np.ndarray, jobs: int, min_matches: int | None = None) -> list[tuple[int, int]]:
    """Contiguous edge ranges [e0, e1) with about equal numbers of matches: at most ``jobs``
    of them and no more than one per ``min_matches`` (default ``MIN_MATCHES_PER_JOB``)
    matches in all (one range when that is impossible)."""
    min_matches = MIN_MATCHES_PER_JOB if min_matches is None else min_matches
    counts = np.asarray(counts, dtype=np.int64)
    E = len(counts)
    total = int(counts.sum())
    parts = int(max(1, min(jobs, E, total // max(min_matches, 1))))
    if parts == 1:
        return [(0, E)]
    before = np.concatenate([[0], np.cumsum(counts)])  # matches before edge b, b = 0..E
    targets = total * np.arange(1, parts) / parts
    right = np.clip(np.searchsorted(before, targets), 1, E)
    # the edge boundary nearest to each equal share
    cuts = np.where(targets - before[right - 1] < before[right] - targets, right - 1, right)
    bounds = np.unique(np.concatenate([[0], cuts, [E]]))
    return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def _send_outcome(conn, fn: Callable, arg) -> None:
    """``fn(arg)``'s outcome through ``conn``: ("ok", value) or ("error", exception), for
    :func:`_receive_outcome` in the parent."""
    try:
        message = ("ok", fn(arg))
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises it
        message = ("error", exc)
    try:
        conn.send(message)
    except Exception as exc:  # the result or the exception did not pickle
        conn.send(("error", RuntimeError(f"worker result could not be sent back: {exc}")))


def _receive_outcome(conn, process):
    """The value a child sent by :func:`_send_outcome`; its exception is raised here, and a
    child that died without sending one raises :class:`WorkerDied`."""
    try:
        status, value = conn.recv()
    except EOFError:
        process.join()
        raise WorkerDied(process.exitcode) from None
    if status == "error":
        raise value
    return value


def _child(conn, fn: Callable, item) -> None:
    try:
        _send_outcome(conn, fn, item)
    finally:
        conn.close()


def fork_map(fn: Callable, items: Sequence) -> list:
    """``[fn(x) for x in items]``: items[1:] in forked children, items[0] in this process.
    ``fn`` may be a closure (nothing is pickled but the results). A child's exception is
    raised here; the item of a child that dies without a result (killed, out of memory) is
    computed here, after a warning."""
    if len(items) <= 1 or not fork_safe():
        return [fn(x) for x in items]
    ctx = mp.get_context("fork")
    children = []
    delivered = False
    try:
        for item in items[1:]:
            children.append(_start_child(ctx, fn, item))
        results = [fn(items[0])]
        for (process, receive), item in zip(children, items[1:]):
            results.append(_receive_or_take_over(receive, process, "worker process", functools.partial(fn, item)))
        delivered = True
        return results
    finally:
        for process, receive in children:
            _reap(process, receive, delivered)


def concat_results(parts: Sequence):
    """Concatenate per-edge dataclass results (arrays along axis 0, nested dataclasses field
    by field) in the order given."""
    first = parts[0]
    values = {}
    for field in dataclasses.fields(first):
        items = [getattr(p, field.name) for p in parts]
        if dataclasses.is_dataclass(items[0]):
            values[field.name] = concat_results(items)
        else:
            values[field.name] = np.concatenate(items, axis=0)
    return type(first)(**values)


def plan(batch, jobs: int) -> list[tuple[int, int]]:
    """The edge ranges to run as separate processes, for :func:`map_edges`: up to ``jobs``
    of them where forking is safe and pays (module docstring), else one (in-process)."""
    return plan_counts(batch.counts, jobs)


def plan_counts(counts: np.ndarray, jobs: int) -> list[tuple[int, int]]:
    """:func:`plan` from the edges' match counts alone (no batch needed yet)."""
    return edge_parts(counts, jobs) if jobs > 1 and fork_safe() else [(0, len(counts))]


def map_edges(fn: Callable, R: np.ndarray, batch, ranges: Sequence[tuple[int, int]]):
    """``fn(R, batch)`` (a per-edge dataclass result) on the edge ``ranges`` of
    :func:`plan`, each in its own process (the first in this one), concatenated."""
    if len(ranges) == 1:
        return fn(R, batch)
    return concat_results(fork_map(lambda r: fn(R[r[0]:r[1]], batch.edge_range(*r)), ranges))


#: matches per chunk of :func:`map_edge_chunks`: a chunk's EdgeBatch (48 B per match), TRRM's
#: MatchTable (104 B) and its per-match temporaries (a few hundred B per match in all) exist for
#: one chunk at a time in each process, so a stage's transient memory no longer grows with the
#: collection's matches (issue 49); 2^19 matches is ~30 edge groups of the lean kernels, whose
#: per-call overhead it keeps amortised
STAGE_CHUNK_MATCHES = 1 << 19


def chunk_ranges(counts: np.ndarray, e0: int, e1: int, chunk: int) -> list[tuple[int, int]]:
    """Consecutive edge ranges covering [e0, e1), each of at most ``chunk`` matches unless a
    single edge has more (kernels.soa.edge_groups' rule)."""
    cum = np.cumsum(np.asarray(counts[e0:e1], dtype=np.int64))
    ranges = []
    a = 0
    while a < e1 - e0:
        base = cum[a - 1] if a else 0
        b = max(int(np.searchsorted(cum, base + chunk, side="right")), a + 1)
        ranges.append((e0 + a, e0 + b))
        a = b
    return ranges


def map_edge_chunks(fn: Callable, R: np.ndarray, counts: np.ndarray, make_batch: Callable,
                    ranges: Sequence[tuple[int, int]], chunk: int | None = None):
    """``fn(R, batch)`` (a per-edge dataclass result) over all edges, batch by batch: each
    of the ``ranges`` (:func:`plan_counts`) in its own process (the first in this one), and
    within it consecutive chunks of about ``chunk`` matches (default ``STAGE_CHUNK_MATCHES``)
    whose batch ``make_batch(e0, e1)`` (edges [e0, e1)) is built, used and released in turn;
    concatenated in edge order. Per-edge results do not depend on the other edges of their
    batch (module docstring), so the chunks change no number."""
    chunk = STAGE_CHUNK_MATCHES if chunk is None else chunk

    def run_range(edge_range: tuple[int, int]):
        parts = [fn(R[a:b], make_batch(a, b)) for a, b in chunk_ranges(counts, *edge_range, chunk)]
        return parts[0] if len(parts) == 1 else concat_results(parts)

    results = fork_map(run_range, ranges) if len(ranges) > 1 else [run_range(ranges[0])]
    return results[0] if len(results) == 1 else concat_results(results)


def shared_array(shape: tuple[int, ...], dtype=np.float64) -> np.ndarray:
    """A zeroed array in an anonymous shared mapping: a child forked after it was made writes
    into the same memory the parent reads (an ordinary array would be copied on write)."""
    count = int(np.prod(shape))
    buffer = mmap.mmap(-1, max(count * np.dtype(dtype).itemsize, 1))  # MAP_SHARED | MAP_ANONYMOUS
    return np.frombuffer(buffer, dtype=dtype, count=count).reshape(shape)


def _serve(conn, handler: Callable) -> None:
    # the parent owns Ctrl-C: it stops this child when it unwinds (ForkedPeer.close)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    while True:
        try:
            message = conn.recv()
        except EOFError:  # the parent is gone
            return
        if message is None:
            return
        _send_outcome(conn, handler, message)


class ForkedPeer:
    """A forked child that answers requests, ``handler(message) -> reply``, one at a time,
    while this process does its own share: :meth:`submit`, then the parent's work, then
    :meth:`collect`. The child sees this process's memory as it was at the fork (closures
    and large arrays need no pickling), and :func:`shared_array` buffers both ways; only the
    messages and replies go through the pipe. Use it as a context manager; only where
    :func:`fork_safe`.

    Should the child die (killed, out of memory), this process answers the pending request
    and every later one itself with the same ``handler``, after a warning: the work costs
    the time of one process, not the run (the handler's results must not depend on the
    process that computes them, as the callers' parts do not). An exception the handler
    raises in the child is raised by :meth:`collect`, as before."""

    #: memory both processes write (made before the fork)
    shared_array = staticmethod(shared_array)

    def __init__(self, handler: Callable):
        ctx = mp.get_context("fork")
        self._handler = handler
        self._pending = None
        self._conn, child_end = ctx.Pipe(duplex=True)
        self._process = ctx.Process(target=_serve, args=(child_end, handler), daemon=True)
        self._process.start()
        child_end.close()

    @property
    def alive(self) -> bool:
        """False once the child died and this process answers the requests."""
        return self._process is not None

    def submit(self, message) -> None:
        self._pending = message
        if self._process is not None:
            try:
                self._conn.send(message)
            except OSError:  # the child is gone: collect() finds out and answers here
                pass

    def collect(self):
        """The reply to the last :meth:`submit`; the child's exception is raised here."""
        message, self._pending = self._pending, None
        if self._process is None:
            return self._handler(message)

        def take_over():
            self.close()  # this process answers every later request too
            return self._handler(message)

        return _receive_or_take_over(self._conn, self._process, "helper process", take_over)

    def close(self) -> None:
        if self._process is None:
            return
        process, self._process = self._process, None
        try:
            self._conn.send(None)
        except OSError:  # the child is gone already
            pass
        _reap(process, self._conn)

    def __enter__(self) -> ForkedPeer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class ForkedCall:
    """``fn()`` started in a forked child where forking is safe (:func:`fork_safe`), else
    called at once in this process; :meth:`result` gives its value (or raises its exception)
    either way, and calls ``fn`` here should the child die without one. For work whose effect
    is a file (written atomically) or a small value, overlapping what this process does next."""

    def __init__(self, fn: Callable, fork: bool = True):
        self._fn = fn
        self._process = None
        self._value = None
        if not (fork and fork_safe()):
            self._value = fn()
            return
        self._process, self._receive = _start_child(mp.get_context("fork"), lambda _: fn(), None)

    def result(self, timeout: float | None = None):
        """``fn()``'s value; TimeoutError if the child has not sent it within ``timeout`` s."""
        if self._process is None:
            return self._value
        if timeout is not None and not self._receive.poll(timeout):
            raise TimeoutError(f"the forked process did not finish within {timeout} s")
        process, self._process = self._process, None
        try:
            self._value = _receive_or_take_over(self._receive, process, "forked process", self._fn)
        finally:
            _reap(process, self._receive)
        return self._value
