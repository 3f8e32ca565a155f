"""Memory guard (issue 49 point 2, issue 53 point 2): before each heavy stage, its peak
resident memory is predicted from the input's counts and compared with the limit in force;
a stage that would not fit is run with smaller chunks where it has any (LiGT), else the run
stops with one line (:class:`~rotonly_cli.errors.OutOfMemoryError`, exit 1) before the stage
allocates anything, and OUT stays as it was (the run builds it in a staging folder).

The limit: the smaller of ``--max-memory`` and the memory this process may still grow to
(MemAvailable of /proc/meminfo plus its own RSS; inside a cgroup v2 / v1 memory limit, that
limit less what the group uses besides this process; under an address-space limit, that limit
less the process's mapped size plus its RSS). GB here is 2**30 bytes, as the
kernel's and ``free -g``'s figures.

The prediction is the process's whole peak RSS during the stage (what it already holds:
the scene, the view graph, Python and the libraries) as ``base`` plus a cost per counted
item (:data:`STAGE_FOOTPRINTS`, one row per stage). The counts are those of the active
edges when the stage starts (GRRM's contribution pairs: sum over observations of k(k-1)/2,
k the matches through the observation; an upper bound of the REGULAR edges' that GRRM
takes). The coefficients were measured on today's code (scripts/bench/memory_calibration.py
prints predicted and measured per stage; docs/tuning.md "Memory guard").
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from rotonly_cli.errors import OutOfMemoryError

logger = logging.getLogger(__name__)

GB = float(1 << 30)
MB = float(1 << 20)


@dataclass(frozen=True)
class Counts:
    """What a stage's memory grows with: inlier matches of the active edges (load: every
    match the input stores), distinct observations (view, keypoint) they touch, keypoints,
    views, active edges, and the pairs of contributions within observations (GRRM)."""

    matches: int = 0
    observations: int = 0
    keypoints: int = 0
    views: int = 0
    edges: int = 0
    pairs: int = 0
    stored_matches: int = 0  #: the input's matches the scene keeps (after load; a stage's own are ``matches``)

    def text(self) -> str:
        """What the error line says the need is for: the load stage's counts are the input's
        (matches, keypoints), the others' the view graph's (observations, pairs too)."""
        parts = [f"{self.matches} matches", f"{self.observations} observations" if self.observations
                 else f"{self.keypoints} keypoints", f"{self.views} views", f"{self.edges} edges"]
        return ", ".join(parts + ([f"{self.pairs} pairs within observations"] if self.pairs else []))


@dataclass(frozen=True)
class Footprint:
    """Peak RSS of a stage in bytes: ``base`` + the per-item costs x :class:`Counts`, plus
    ``per_chunk_row`` x the stage's chunk (LiGT's constraints per chunk, at most one per
    observation), the part that smaller chunks save."""

    base: float
    per_match: float = 0.0
    per_observation: float = 0.0
    per_keypoint: float = 0.0
    per_view: float = 0.0
    per_edge: float = 0.0
    per_pair: float = 0.0
    per_chunk_row: float = 0.0
    per_stored_match: float = 0.0
    #: the cost of a stage that works through its matches in groups of at most ``chunk_matches``
    per_chunk_match: float = 0.0
    chunk_matches: int = 0

    def bytes(self, counts: Counts, chunk: int = 0) -> float:
        return (self.base + self.per_match * counts.matches + self.per_observation * counts.observations
                + self.per_chunk_match * min(counts.matches, self.chunk_matches)
                + self.per_keypoint * counts.keypoints + self.per_view * counts.views + self.per_edge * counts.edges
                + self.per_pair * counts.pairs + self.per_chunk_row * min(chunk, counts.observations or chunk)
                + self.per_stored_match * counts.stored_matches)


#: the interpreter with numpy, scipy and pycolmap imported, before any input is read (measured: 126-157
#: MiB through a run of a 4-view database)
PROCESS_BASE = 160 * MB
#: what every stage after load holds: the scene's stored matches (int64 pairs) and keypoints (pixel and
#: normalized coordinates), from the arrays' layout
HELD = {"per_stored_match": 20.0, "per_keypoint": 48.0}
#: Per stage, the process's peak RSS (bytes). The per-match (and GRRM's per-pair) costs are fitted to
#: the peaks measured on /work/scale/v200 (circular, 200 views, 4.4 M inlier matches, 569 k observations,
#: 69 M pairs within observations) and on a circular 60-view window-15 scene (0.91 M matches, 82 k
#: observations, 21 M pairs: longer tracks) by scripts/bench/memory_calibration.py, the larger of the two
#: plus 10 %; GRRM's two costs solve both scenes (31 B per pair: its pair_a, pair_b, pair_block int64
#: arrays and a key). Recalibrate here when a stage's memory changes (GRRM without the pair lists: its
#: per_pair goes to 0). docs/tuning.md "Memory guard" has the table of predicted against measured.
#: Recalibrated since on today's code with scripts/bench/memory_calibration.py --no-limit (each stage's
#: own peak) on three of scripts/bench/scale.py's collections, circular 200 views (4.4 M matches),
#: 50 views seeing ~31 each (6.1 M) and circular 1000 views (21 M): each stage's per-match cost the
#: largest of the three plus 10 %, the rest as it was; they predict the measured peaks 3-26 % high
#: (docs/tuning.md "Memory guard", the table of the refit).
STAGE_FOOTPRINTS: dict[str, Footprint] = {
    "load": Footprint(PROCESS_BASE, per_match=19.0, per_keypoint=48.0),  # matches: every row the database stores
    # identify, refine: edges in groups of 2^19 matches (runtime/parallel.STAGE_CHUNK_MATCHES), each a
    # batch and MatchTable (~210 B per match) freed before the next
    "identify": Footprint(PROCESS_BASE, per_match=15.0, per_chunk_match=230.0, chunk_matches=1 << 19, **HELD),
    "refine": Footprint(PROCESS_BASE, per_match=15.0, per_chunk_match=250.0, chunk_matches=1 << 19, **HELD),
    # and the minority-keypoint drop's track tables (two int64 keys, int32 nodes, the match graph):
    # measured 2.05 GB at 1000 views (21 M matches), 1.06 GB before it
    "average": Footprint(PROCESS_BASE, per_match=75.0, **HELD),
    # GRRM: no pair lists (grrm/layout.py); per match its observation rows, the layout's two int32
    # per contribution, the weights and the layout's sort, and the parts' tables, gathered coordinates
    # and work (the fit gives them no cost of their own: 128 B per match and -53 per chunk match)
    "optimize": Footprint(PROCESS_BASE, per_match=141.0, **HELD),
    "translate": Footprint(PROCESS_BASE, per_match=95.0, per_chunk_row=2000.0, **HELD),
    "reject": Footprint(PROCESS_BASE, per_match=52.0, per_chunk_row=2000.0, **HELD),  # and GRRM's, LiGT's: predict
    "triangulate": Footprint(PROCESS_BASE, per_match=104.0, **HELD),
    "export": Footprint(PROCESS_BASE, per_match=121.0, **HELD),
}
#: smallest LiGT chunk the guard degrades to (constraints per chunk; LiGTOptions.chunk_size)
MIN_CHUNK = 2_000
LIGT_CHUNK = 50_000  #: LiGTOptions.chunk_size's default
#: the stages that run LiGT (in chunks the guard may make smaller)
LIGT_STAGES = ("translate", "reject")
#: reset VmHWM before each stage and record the measured peak beside the prediction (the
#: calibration script sets it; not in a user's run: the reset also lowers what
#: getrusage / `time -v` report as the process's peak)
MEASURE_PEAKS = False


def predict(stage: str, counts: Counts, chunk: int = LIGT_CHUNK, grrm: bool = True) -> float:
    """The predicted peak RSS (bytes) of ``stage``; the reject stage's covers the GRRM (with
    ``grrm``) and LiGT it may run again."""
    need = STAGE_FOOTPRINTS[stage].bytes(counts, chunk)
    if stage == "reject":
        need = max(need, predict("translate", counts, chunk), predict("optimize", counts) if grrm else 0.0)
    return need


def gb_texts(*values: float) -> list[str]:
    """``values`` (bytes) in GB, one decimal (two below 1 GB), more where they would read alike."""
    digits = 1 if min(values) >= GB else 2
    while True:
        texts = [f"{value / GB:.{digits}f}" for value in values]
        if len(set(texts)) == len(texts) or digits >= 4:
            return texts
        digits += 1


# ============================================================================ the limit

def _read_int(path: Path) -> int | None:
    try:
        text = path.read_text().split()[0]
    except (OSError, IndexError):
        return None
    return int(text) if text.isdigit() else None


def _status_kb(key: str, path: str = "/proc/self/status") -> int | None:
    try:
        with open(path) as status:
            for line in status:
                if line.startswith(key + ":"):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


def rss_bytes() -> int:
    """This process's resident memory now (0 where /proc is not there)."""
    return (_status_kb("VmRSS") or 0) * 1024


def _cgroup_headroom(own_rss: int) -> int | None:
    """What a cgroup v2 or v1 memory limit leaves this process (limit - the group's usage
    other than its page cache - ... + own RSS); None without a limit."""
    try:
        lines = Path("/proc/self/cgroup").read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        hierarchy, _, rest = line.partition(":")
        controllers, _, group = rest.partition(":")
        group = group.lstrip("/")
        if hierarchy == "0" and controllers == "":  # v2
            names, roots = ("memory.max", "memory.current", "inactive_file"), ["/sys/fs/cgroup"]
        elif "memory" in controllers.split(","):  # v1
            names = ("memory.limit_in_bytes", "memory.usage_in_bytes", "total_inactive_file")
            roots = ["/sys/fs/cgroup/memory"]
        else:
            continue
        for root in roots:
            for directory in (Path(root) / group, Path(root)):
                limit = _read_int(directory / names[0])
                if limit is None or limit >= 1 << 60:  # "max" or v1's unlimited
                    continue
                usage = _read_int(directory / names[1]) or 0
                cache = _stat_value(directory / "memory.stat", names[2])
                return max(0, limit - max(0, usage - cache) + own_rss)
    return None


def _stat_value(path: Path, key: str) -> int:
    try:
        for line in path.read_text().splitlines():
            name, _, value = line.partition(" ")
            if name == key:
                return int(value)
    except (OSError, ValueError):
        pass
    return 0


def _address_space_headroom(own_rss: int) -> int | None:
    """What an address-space limit (``ulimit -v``, ``prlimit --as``) leaves the process's RSS
    (new allocations grow both): the limit less its mapped size, plus its RSS; None without one."""
    import resource

    soft = resource.getrlimit(resource.RLIMIT_AS)[0]
    mapped = _status_kb("VmSize")
    if soft == resource.RLIM_INFINITY or mapped is None:
        return None
    return max(0, soft - mapped * 1024 + own_rss)


#: what the two OpenBLAS libraries (numpy's, scipy's) map for their buffers at their first call,
#: 32 MiB each (measured: VmSize +32 MiB at numpy's first gemm and at scipy's first trsv). Under an
#: address-space limit a failed mapping is not a MemoryError: OpenBLAS retries for ever (scipy's:
#: a run hung at 100 % CPU in SuperLU's first solve) or exits with its own message (numpy's)
BLAS_BUFFERS = 64 * MB
#: room a run needs beyond what is mapped at its start: the BLAS buffers and the stacks of the
#: load stage's threads (8 MiB each; a thread that cannot map its stack fails in a way Python
#: cannot always report: Thread.start() may wait for ever)
START_ROOM = BLAS_BUFFERS + 64 * MB


def reserve_blas_buffers() -> None:
    """Make numpy's and scipy's OpenBLAS map their buffers now, at the start of a run, when
    the room for them is checked: OutOfMemoryError when an address-space limit leaves less
    than :data:`START_ROOM` (their first use later in a run, under the limit, would hang or
    end the process without rotonly's error line). The buffers are kept for the process's
    life (and inherited by its forked workers); a second call costs nothing."""
    import resource

    soft = resource.getrlimit(resource.RLIMIT_AS)[0]
    mapped = _status_kb("VmSize")
    if soft != resource.RLIM_INFINITY and mapped is not None and soft - mapped * 1024 < START_ROOM:
        need, limit = gb_texts(mapped * 1024 + START_ROOM, soft)
        raise OutOfMemoryError(f"the run needs about {need} GB of address space to start (the BLAS buffers and "
                               f"threads), above the limit of {limit} GB (address-space limit)")
    import scipy.linalg.blas

    identity = np.eye(64)
    identity @ identity  # numpy's: its gemm takes the buffer
    scipy.linalg.blas.dtrsv(identity[:4, :4], np.ones(4))  # scipy's (SuperLU's solves use trsv)


def available_bytes() -> int | None:
    """The memory this process may grow to: MemAvailable + its own RSS, within a cgroup
    memory limit and an address-space limit if set; None where none is known (not Linux)."""
    own = rss_bytes()
    free_kb = _status_kb("MemAvailable", "/proc/meminfo")
    candidates = [] if free_kb is None else [free_kb * 1024 + own]
    candidates += [room for room in (_cgroup_headroom(own), _address_space_headroom(own)) if room is not None]
    return min(candidates) if candidates else None


@dataclass(frozen=True)
class Limit:
    bytes: float | None  #: None: no limit known
    source: str  #: "--max-memory" or "available memory"

    @staticmethod
    def in_force(max_memory_gb: float | None) -> Limit:
        available = available_bytes()
        given = None if max_memory_gb is None else max_memory_gb * GB
        if given is not None and (available is None or given <= available):
            return Limit(given, "--max-memory")
        return Limit(None if available is None else float(available), "available memory")


# ============================================================================ counts

def graph_counts(graph, normalized: dict[int, np.ndarray], stored_matches: int = 0) -> Counts:
    """:class:`Counts` of the active edges of ``graph`` (scene.view_graph.ViewGraph);
    ``stored_matches``: the matches the scene holds besides (:func:`scene_counts`)."""
    active = graph.active_edges()
    indices: dict[int, list[np.ndarray]] = {}  # per view, the keypoint of every match side there
    matches = 0
    for k in active:
        edge = graph.edges[k]
        matches += len(edge.matches)
        indices.setdefault(edge.i, []).append(edge.matches[:, 0])
        indices.setdefault(edge.j, []).append(edge.matches[:, 1])
    per_view = {view: np.bincount(np.concatenate(parts), minlength=len(normalized.get(view, ())))
                for view, parts in indices.items()}
    observations = pairs = 0
    for through in per_view.values():
        k = through[through > 0].astype(np.int64)
        observations += len(k)
        pairs += int((k * (k - 1) // 2).sum())
    keypoints = sum(len(points) for points in normalized.values())
    return Counts(matches, observations, keypoints, len(graph.views), len(active), pairs, stored_matches)


def scene_counts(scene, graph) -> Counts:
    """:func:`graph_counts` of a run's view graph, with the matches its scene (SfMScene) holds."""
    return graph_counts(graph, scene.normalized, sum(len(pair.matches) for pair in scene.pairs.values()))


def database_counts(path: str | Path) -> Counts | None:
    """:class:`Counts` of a COLMAP database before it is read (the load stage reads the
    verified and the raw matches both); None where the tables cannot be counted. Read as
    io/colmap/database_check reads an input: a rollback-journal file under SQLite's locks (a
    writer's pages half written would count wrong), for a second at most; WAL ``immutable``."""
    import sqlite3

    try:
        path = Path(path).resolve()
        with open(path, "rb") as stream:
            header = stream.read(20)
        wal = len(header) == 20 and header[18] == 2  # the file format's versions: 2 WAL, 1 rollback journal
        connection = sqlite3.connect(f"{path.as_uri()}?mode=ro{'&immutable=1' if wal else ''}", uri=True, timeout=1.0)
    except (OSError, sqlite3.Error, ValueError):
        return None
    try:
        one = lambda sql: connection.execute(sql).fetchone()  # noqa: E731
        views = one("SELECT COUNT(*) FROM images")[0]
        keypoints = one("SELECT COALESCE(SUM(rows), 0) FROM keypoints")[0]
        raw, pairs = one("SELECT COALESCE(SUM(rows), 0), COUNT(*) FROM matches")
        verified, verified_pairs = one("SELECT COALESCE(SUM(rows), 0), COUNT(*) FROM two_view_geometries")
    except sqlite3.Error:
        return None
    finally:
        connection.close()
    return Counts(matches=int(raw) + int(verified), keypoints=int(keypoints), views=int(views),
                  edges=int(max(pairs, verified_pairs)))


# ============================================================================ the guard

@dataclass
class Prediction:
    stage: str
    bytes: float
    counts: Counts
    chunk: int | None = None  #: LiGT's chunk, when the guard made it smaller (at this stage or before)
    measured_bytes: float | None = None

    def record(self) -> dict:
        entry = {"stage": self.stage, "predicted_gb": round(self.bytes / GB, 3), "counts": asdict(self.counts)}
        if self.chunk is not None:
            entry["chunk_size"] = self.chunk
        if self.measured_bytes is not None:
            entry["measured_gb"] = round(self.measured_bytes / GB, 3)
        return entry


def _reset_peak() -> None:
    try:
        with open("/proc/self/clear_refs", "w") as clear_refs:
            clear_refs.write("5")
    except OSError:
        pass


#: [stage, Prediction | None] of the guarded stage in progress, or of the one an error left
LAST_STAGE: list = [None, None]
#: [the last guarded stage that ended, its prediction]: named by an error between stages
LAST_DONE: list = [None, None]


@dataclass
class MemoryGuard:
    """One run's guard: ``with guard.stage(name, counts, run_options) as options:`` checks
    before the stage (raising OutOfMemoryError), hands back the options it is to run with
    (smaller chunks), turns a MemoryError inside into OutOfMemoryError, and records."""

    max_memory_gb: float | None = None
    predictions: list[Prediction] = field(default_factory=list)
    limit: Limit | None = None
    current: Prediction | None = None

    def __post_init__(self) -> None:
        LAST_STAGE[:] = LAST_DONE[:] = [None, None]  # a new run: no stage of an earlier one is named
        reserve_blas_buffers()

    def check(self, stage: str, counts: Counts, options=None):
        """The options ``stage`` runs with (``options``, or with a smaller LiGT chunk); raises
        OutOfMemoryError when even that does not fit."""
        self.limit = limit = Limit.in_force(self.max_memory_gb)
        if stage not in STAGE_FOOTPRINTS:
            return options
        chunk = options.translate.chunk_size if options is not None else LIGT_CHUNK
        need = predict(stage, counts, chunk, options is None or options.grrm)
        degraded = False
        if limit.bytes is not None and need > limit.bytes and chunk and stage in LIGT_STAGES:
            while chunk > MIN_CHUNK and need > limit.bytes:
                chunk, degraded = max(MIN_CHUNK, chunk // 2), True
                need = predict(stage, counts, chunk, options is None or options.grrm)
            options = replace(options, translate=replace(options.translate, chunk_size=chunk))
        smaller = chunk if stage in LIGT_STAGES and chunk < LIGT_CHUNK else None  # made smaller, here or before
        self.current = Prediction(stage, need, counts, smaller)
        self.predictions.append(self.current)
        if limit.bytes is not None and need > limit.bytes:
            shown_need, shown_limit = gb_texts(need, limit.bytes)
            raise OutOfMemoryError(f"{stage} needs about {shown_need} GB ({counts.text()}), above the limit of "
                                   f"{shown_limit} GB ({limit.source})")
        if degraded:
            logger.info("%s: LiGT in chunks of %d constraints to fit in %s GB (%s)", stage, smaller,
                        gb_texts(limit.bytes)[0], limit.source)
        return options

    @contextmanager
    def stage(self, stage: str, counts: Counts | None, options=None) -> Iterator:
        if counts is not None:
            options = self.check(stage, counts, options)
        else:
            self.current = None
        if MEASURE_PEAKS:
            _reset_peak()
        previous = LAST_STAGE[:]
        LAST_STAGE[:] = [stage, self.current]
        try:
            yield options
        except MemoryError as exc:
            raise self.out_of_memory(stage, exc) from None
        finally:
            if MEASURE_PEAKS and self.current is not None:
                self.current.measured_bytes = (_status_kb("VmHWM") or 0) * 1024.0
        LAST_STAGE[:] = previous  # left as it was on an error: the CLI names the stage of a stray one
        LAST_DONE[:] = [stage, self.current]

    def out_of_memory(self, stage: str, exc: MemoryError) -> OutOfMemoryError:
        """The one-line error of a MemoryError raised in ``stage``."""
        return out_of_memory_error(stage, exc, self.current if self.current and self.current.stage == stage else None)

    def record(self) -> dict:
        limit = self.limit or Limit.in_force(self.max_memory_gb)
        return {"limit_gb": None if limit.bytes is None else round(limit.bytes / GB, 3), "limit_source": limit.source,
                "max_memory_gb": self.max_memory_gb, "stages": [p.record() for p in self.predictions]}


def out_of_memory_error(stage: str | None, exc: BaseException, prediction: Prediction | None = None,
                        after: str | None = None) -> OutOfMemoryError:
    """``error: <stage> ran out of memory (<the allocation's message>)``, with the predicted
    need where known; outside any guarded stage, ``out of memory after the <after> stage``."""
    message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    need = "" if prediction is None else (f"; it needs about {gb_texts(prediction.bytes)[0]} GB "
                                          f"({prediction.counts.text()})")
    where = (f"{stage} ran out of memory" if stage else f"out of memory after the {after} stage" if after
             else "out of memory")
    return OutOfMemoryError(f"{where} ({message}){need}")
