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
its result (killed, out of memory), or that the system refuses to start (fork failing with
EAGAIN / ENOMEM), costs time, not the run: this process computes its part, after a warning.

No child outlives the run (issue 53): each child first asks the kernel for SIGKILL when its
parent dies (``PR_SET_PDEATHSIG``; the parent is the main thread, the only one alive when
forking is safe) and checks that the parent is still there (it may have died before the
request), then closes its copies of the parent's ends of every child's pipe, so that a child
blocked reading sees EOF once the parent is gone. Ctrl-C is deferred while a child is forked
and delivered right after: raised inside the at-fork hooks (logging's), a KeyboardInterrupt
is only printed ("Exception ignored") and lost.
"""

from __future__ import annotations

import ctypes
import dataclasses
import functools
import logging
import mmap
import multiprocessing as mp
import os
import signal
import sys
import threading
import weakref
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager

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
    _PARENT_ENDS.add(receive)  # before the fork: the child closes its copy
    process = ctx.Process(target=_child, args=(send, fn, item, os.getpid()), daemon=True)
    try:
        process.start()
    except BaseException:
        receive.close()
        raise
    finally:
        send.close()  # the child holds the write end
    return process, receive


def _start_into(children: list, ctx, fn: Callable, item) -> None:
    """Append :func:`_start_child`'s (process, pipe) to ``children`` with Ctrl-C deferred during
    the fork (:func:`_interrupts_deferred`; appended before a deferred Ctrl-C is raised, so the
    caller reaps the child), or None, after a warning, when the system refuses a process (the caller then
    computes ``fn(item)`` itself)."""
    try:
        with _interrupts_deferred():
            children.append(_start_child(ctx, fn, item))
    except OSError as exc:  # fork: EAGAIN (process limit), ENOMEM
        logger.warning("no worker process could be started (%s): its work is done in this process",
                       exc.strerror or exc)
        children.append(None)


#: prctl(2) option: the signal a process gets when the thread that forked it ends (Linux)
_PR_SET_PDEATHSIG = 1


def _libc_prctl():
    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (AttributeError, OSError):  # not glibc / not Linux
        return None


_prctl = _libc_prctl() if sys.platform.startswith("linux") else None

#: this process's (open) ends of its children's pipes. A child forked later inherits copies of
#: them; were they kept, a child blocked reading its own pipe would never see EOF after the
#: parent died (the parent's end would still be open, in the child itself or a sibling)
_PARENT_ENDS: weakref.WeakSet = weakref.WeakSet()

#: the SIGINT handler in force before :func:`_interrupts_deferred` replaced it (None outside
#: it): a forked child takes it back
_SIGINT_BEFORE_FORK: list = [None]


@contextmanager
def _interrupts_deferred() -> Iterator[None]:
    """Ctrl-C recorded, not raised, while the block forks a child; delivered again
    (``raise_signal``) when the block ends, its KeyboardInterrupt raised there. Python runs
    signal handlers between bytecodes, also inside the at-fork hooks that ``os.fork`` calls
    (logging's), which print an exception raised there ("Exception ignored") and drop it: a
    Ctrl-C during a fork was lost. Blocking SIGINT (pthread_sigmask) would not do: the kernel
    gives a process's signal to any thread that does not block it (a BLAS pool's)."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGINT) is None:
        yield
        return
    received = []
    _SIGINT_BEFORE_FORK[0] = signal.signal(signal.SIGINT, lambda number, frame: received.append(number))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, _SIGINT_BEFORE_FORK[0])
        _SIGINT_BEFORE_FORK[0] = None
        if received:
            signal.raise_signal(signal.SIGINT)


def _enter_child(parent: int, sigint=None) -> None:
    """What a forked child does first: be killed when ``parent`` dies (PR_SET_PDEATHSIG, then a
    check that it did not die before the request: the kernel would not send the signal), close
    its copies of the parent's pipe ends, then take ``sigint`` as its Ctrl-C handler (default:
    the parent's before the fork, :func:`_interrupts_deferred`)."""
    if _prctl is not None:
        _prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    if os.getppid() != parent:  # the parent is gone already: nobody reads this child's result
        os._exit(1)
    for end in list(_PARENT_ENDS):
        end.close()
    handler = sigint if sigint is not None else _SIGINT_BEFORE_FORK[0]
    if handler is not None:
        signal.signal(signal.SIGINT, handler)
        _SIGINT_BEFORE_FORK[0] = None


def _reap(process, conn, delivered: bool = True) -> None:
    """Close this end of the child's pipe and end the child: one that delivered its result
    exits by itself, the others are killed (SIGKILL: pycolmap's failure handler answers SIGTERM
    with a stack trace on the run's stderr, seen after a Ctrl-C; a child holds nothing that
    needs cleaning up, its files are in the run's staging folder)."""
    conn.close()
    if delivered:
        process.join(timeout=DELIVERED_EXIT_TIMEOUT_S)
    if process.is_alive():
        process.kill()
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


#: predicates of threads a fork may leave behind (runtime/cluster registers the Dask client's:
#: registered from there, so this module does not import the cluster's)
FORK_SAFE_THREADS: list[Callable[[threading.Thread], bool]] = []


def _no_other_threads() -> bool:
    """No Python thread alive but this one, or only the Dask client's of a ``--cluster`` run
    (runtime/cluster.owns_thread, in FORK_SAFE_THREADS): those run its event loop and never
    touch what a forked child does (a child answers from its own copy of the memory and exits
    with os._exit)."""
    others = [t for t in threading.enumerate() if t is not threading.current_thread()]
    return all(any(safe(t) for safe in FORK_SAFE_THREADS) for t in others)


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
    except Exception as exc:  # the result or the exception did not pickle, or no memory was left for it
        failed = message[1] if message[0] == "error" else None
        if isinstance(failed, MemoryError) or isinstance(exc, MemoryError):
            # out of memory stays out of memory in the parent (one error line, cli.main), whatever
            # the numpy subclass or the pickling made of it
            memory_error = failed if isinstance(failed, MemoryError) else exc
            conn.send(("error", MemoryError(str(memory_error) or "out of memory in a worker process")))
        else:
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


def _child(conn, fn: Callable, item, parent: int) -> None:
    _enter_child(parent)
    try:
        _send_outcome(conn, fn, item)
    except BaseException:  # noqa: BLE001 - nothing could be sent (no memory left even for the error,
        # the parent gone): the parent sees EOF and does the work itself; no traceback on the run's stderr
        os._exit(1)
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
    children = []  # (process, pipe), or None where no process could be started
    delivered = False
    try:
        for item in items[1:]:
            _start_into(children, ctx, fn, item)
        results = [fn(items[0])]
        for child, item in zip(children, items[1:]):
            if child is None:
                results.append(fn(item))
                continue
            process, receive = child
            results.append(_receive_or_take_over(receive, process, "worker process", functools.partial(fn, item)))
        delivered = True
        return results
    finally:
        for child in children:
            if child is not None:
                _reap(*child, delivered)


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


def _serve(conn, handler: Callable, parent: int) -> None:
    # the parent owns Ctrl-C: it stops this child when it unwinds (ForkedPeer.close)
    _enter_child(parent, sigint=signal.SIG_IGN)
    try:
        while True:
            try:
                message = conn.recv()
            except EOFError:  # the parent is gone
                return
            if message is None:
                return
            _send_outcome(conn, handler, message)
    except BaseException:  # noqa: BLE001 - as in _child: the parent sees EOF and answers itself
        os._exit(1)


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
        self._process = None
        self._conn, child_end = ctx.Pipe(duplex=True)
        _PARENT_ENDS.add(self._conn)  # before the fork: the child closes its copy
        process = ctx.Process(target=_serve, args=(child_end, handler, os.getpid()), daemon=True)
        try:
            with _interrupts_deferred():
                try:
                    process.start()
                    self._process = process
                except OSError as exc:  # fork refused (EAGAIN, ENOMEM): this process answers every request
                    logger.warning("no helper process could be started (%s): its work is done in this process",
                                   exc.strerror or exc)
                    self._conn.close()
                finally:
                    child_end.close()
        except BaseException:  # a Ctrl-C deferred during the fork: the child is stopped before it is raised
            self.close()
            raise

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
        # a request still pending (the parent unwinds from an error or Ctrl-C): not waited for
        _reap(process, self._conn, delivered=self._pending is None)

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
        children = []
        try:
            _start_into(children, mp.get_context("fork"), lambda _: fn(), None)
        except BaseException:  # a Ctrl-C deferred during the fork: the child is stopped before it is raised
            for child in children:
                if child is not None:
                    _reap(*child, delivered=False)
            raise
        if children[0] is None:
            self._value = fn()
            return
        self._process, self._receive = children[0]

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
