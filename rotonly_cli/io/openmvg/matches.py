"""OpenMVG matches files (``matches.*.txt|bin``, formats.md §2.4–§2.5) and pairs files (§2.6)."""

from __future__ import annotations

import os
import struct
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.io import atomic
from rotonly_cli.io.openmvg.features import read_bytes
from rotonly_cli.scene.types import PairMatches

PathLike = str | os.PathLike


# ============================================================================ matches

MatchesDict = dict[tuple[int, int], np.ndarray]


def _add_pair(matches: MatchesDict, view_i: int, view_j: int, pair_matches: np.ndarray,
              path: PathLike, where: str) -> None:
    """Store with key (min, max) and columns swapped accordingly (scene/types.py convention)."""
    if view_i == view_j:
        raise InputError(f"pair ({view_i}, {view_j}) matches a view with itself",
                         path=str(path), field=where)
    if view_i > view_j:
        view_i, view_j, pair_matches = view_j, view_i, pair_matches[:, ::-1]
    if (view_i, view_j) in matches:
        raise InputError(f"pair ({view_i}, {view_j}) appears twice", path=str(path), field=where)
    matches[(view_i, view_j)] = np.ascontiguousarray(pair_matches, dtype=np.int64)


def _read_matches_bin(path: PathLike) -> MatchesDict:
    """cereal PortableBinary PairWiseMatches (formats.md §2.5): u8 endianness flag, u64
    n_pairs, then per pair u32 I, u32 J, u64 n, n x (u32 i, u32 j)."""
    payload = read_bytes(path)
    if len(payload) < 9:
        raise InputError(f"truncated: {len(payload)} bytes, header needs 9", path=str(path),
                         field="header")
    if payload[0] != 1:
        raise InputError(f"endianness flag {payload[0]} is not 1 (little-endian)",
                         path=str(path), field="header")
    (num_pairs,) = struct.unpack_from("<Q", payload, 1)
    offset = 9
    matches: MatchesDict = {}
    pair_header = struct.Struct("<IIQ")
    for pair_index in range(num_pairs):
        where = f"pair {pair_index}"
        if offset + pair_header.size > len(payload):
            raise InputError(f"truncated: header of pair {pair_index} of {num_pairs} is missing "
                             f"(byte {offset} of {len(payload)})", path=str(path), field=where)
        view_i, view_j, num_matches = pair_header.unpack_from(payload, offset)
        offset += pair_header.size
        end = offset + 8 * num_matches
        if end > len(payload):
            raise InputError(f"truncated: pair ({view_i}, {view_j}) announces {num_matches} "
                             f"matches, only {(len(payload) - offset) // 8} present",
                             path=str(path), field=where)
        pair_matches = np.frombuffer(payload, dtype="<u4", count=2 * num_matches,
                                     offset=offset).reshape(-1, 2)
        offset = end
        _add_pair(matches, view_i, view_j, pair_matches, path, where)
    if offset != len(payload):
        raise InputError(f"{len(payload) - offset} unexpected bytes after {num_pairs} pairs",
                         path=str(path), field="trailer")
    return matches


def _read_matches_txt(path: PathLike) -> MatchesDict:
    """Text matches (formats.md §2.4): ``I J`` / ``N`` / N lines ``i j``, repeated."""
    payload = read_bytes(path)
    text = payload.decode("ascii", errors="replace")
    tokens = text.split()
    try:
        values = np.array(tokens, dtype=np.int64)
    except ValueError:
        raise InputError("non-integer token", path=str(path)) from None
    if np.any(values < 0) or np.any(values > 0xFFFFFFFF):
        raise InputError("negative or > 32-bit index", path=str(path))
    matches: MatchesDict = {}
    position = 0
    pair_index = 0
    while position < values.size:
        where = f"pair {pair_index}"
        if position + 3 > values.size:
            raise InputError("truncated pair header (expected 'I J' then 'N')", path=str(path),
                             field=where)
        view_i, view_j, num_matches = (int(v) for v in values[position:position + 3])
        position += 3
        if position + 2 * num_matches > values.size:
            raise InputError(f"truncated: pair ({view_i}, {view_j}) announces {num_matches} "
                             "matches", path=str(path), field=where)
        block = values[position:position + 2 * num_matches].reshape(-1, 2)
        position += 2 * num_matches
        _add_pair(matches, view_i, view_j, block, path, where)
        pair_index += 1
    return matches


def read_matches(path: PathLike) -> MatchesDict:
    """``matches.*.bin`` (cereal binary) or ``matches.*.txt`` -> {(i, j): (m, 2) int64}, i < j."""
    if str(path).endswith(".bin"):
        return _read_matches_bin(path)
    return _read_matches_txt(path)


def _sorted_match_arrays(
        matches: Mapping[tuple[int, int], Any]) -> list[tuple[int, int, np.ndarray]]:
    rows = []
    for (view_i, view_j), value in matches.items():
        array = value.matches if isinstance(value, PairMatches) else value
        array = np.asarray(array, dtype=np.int64).reshape(-1, 2)
        if np.any(array < 0) or np.any(array > 0xFFFFFFFF):
            raise InputError(f"pair ({view_i}, {view_j}): index outside uint32",
                             field="matches")
        rows.append((int(view_i), int(view_j), array))
    rows.sort(key=lambda row: (row[0], row[1]))  # std::map<Pair,...> order (§2.4)
    return rows


def matches_bytes(matches: Mapping[tuple[int, int], Any], binary: bool) -> bytes:
    rows = _sorted_match_arrays(matches)
    if binary:
        chunks = [struct.pack("<BQ", 1, len(rows))]
        for view_i, view_j, array in rows:
            chunks.append(struct.pack("<IIQ", view_i, view_j, array.shape[0]))
            chunks.append(array.astype("<u4").tobytes())
        return b"".join(chunks)
    chunks_text = []
    for view_i, view_j, array in rows:
        chunks_text.append(f"{view_i} {view_j}\n{array.shape[0]}\n")
        chunks_text.append(("%d %d\n" * array.shape[0]) % tuple(array.ravel().tolist()))
    return "".join(chunks_text).encode("ascii")


def write_matches(path: PathLike, matches: Mapping[tuple[int, int], Any]) -> None:
    """Write {(i, j): (m, 2)} (or PairMatches values) as ``.bin`` (cereal) or text."""
    atomic.write_bytes(path, matches_bytes(matches, binary=str(path).endswith(".bin")))


def read_pairs(path: PathLike, num_views: int | None = None) -> list[tuple[int, int]]:
    """Pairs file (formats.md §2.6: always text, adjacency lines ``I J1 J2 ...``) -> sorted
    unique (min, max) pairs; rejects I == J and, given ``num_views``, ids >= num_views."""
    text = read_bytes(path).decode("ascii", errors="replace")
    pairs: set[tuple[int, int]] = set()
    for line_number, line in enumerate(text.splitlines(), start=1):
        tokens = line.split()
        if not tokens:
            continue
        if len(tokens) < 2:
            raise InputError("expected 'I J1 J2 ...'", path=str(path), field=f"line {line_number}")
        try:
            ids = [int(token) for token in tokens]
        except ValueError:
            raise InputError("non-integer view id", path=str(path),
                             field=f"line {line_number}") from None
        for other in ids[1:]:
            if other == ids[0] or min(ids[0], other) < 0 or (
                    num_views is not None and max(ids[0], other) >= num_views):
                raise InputError(f"invalid pair ({ids[0]}, {other})", path=str(path),
                                 field=f"line {line_number}")
            pairs.add((min(ids[0], other), max(ids[0], other)))
    return sorted(pairs)


def write_pairs(path: PathLike, pairs: Iterable[tuple[int, int]]) -> None:
    """Text ``I J`` lines, sorted (what OpenMVG's savePairs writes, even for ``pairs.bin``)."""
    ordered = sorted({(min(int(i), int(j)), max(int(i), int(j))) for i, j in pairs})
    atomic.write_bytes(path, "".join(f"{i} {j}\n" for i, j in ordered).encode("ascii"))
