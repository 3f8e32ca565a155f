"""OpenMVG ``<stem>.feat`` feature files (formats.md §2.2)."""

from __future__ import annotations

import os
import warnings

import numpy as np

from rotonly_cli.errors import InputError
from rotonly_cli.io import atomic, inputs
from rotonly_cli.io.openmvg.cameras import to_colmap_pixels, to_openmvg_pixels

PathLike = str | os.PathLike


# ============================================================================ .feat files

def read_bytes(path: PathLike) -> bytes:
    """The content of a regular file (io/inputs: pipes and devices are refused unopened)."""
    return inputs.read_bytes(path)


def _tokens_per_line(payload: bytes) -> tuple[np.ndarray, int]:
    """Number of whitespace-separated tokens on each line (vectorised over the bytes), and
    the total token count."""
    data = np.frombuffer(payload, dtype=np.uint8)
    if data.size == 0:
        return np.zeros(0, dtype=np.int64), 0
    whitespace = (data == 32) | (data == 9) | (data == 13) | (data == 10) | (data == 11) | (
        data == 12)
    token_start = ~whitespace
    token_start[1:] &= whitespace[:-1]
    starts = np.flatnonzero(token_start)
    newlines = np.flatnonzero(data == 10)
    line_of_token = np.searchsorted(newlines, starts)
    counts = np.bincount(line_of_token, minlength=newlines.size + 1)
    return counts, starts.size


def read_feature_table(path: PathLike) -> np.ndarray:
    """(n, 4) ``x y scale orientation`` rows of a ``.feat`` file, x/y still in OpenMVG's
    pixel convention (formats.md §2.2). Blank lines are ignored; every other line must have
    exactly 4 columns (line index = feature index = ``id_feat``)."""
    payload = read_bytes(path)
    counts, num_tokens = _tokens_per_line(payload)
    bad_lines = np.flatnonzero((counts != 4) & (counts != 0))
    if bad_lines.size:
        line = int(bad_lines[0])
        raise InputError(f"{int(counts[line])} columns, expected 4 "
                         "(x y scale orientation)", path=str(path), field=f"line {line + 1}")
    if num_tokens == 0:
        return np.zeros((0, 4))
    # np.fromstring(sep=" ") is numpy's C text-to-double parser (about 3x faster than
    # np.array(bytes.split(), float)); any whitespace separates. A bad token raises (numpy 2)
    # or stops the parse early (older numpy: DeprecationWarning), hence the size check.
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            values = np.fromstring(payload.decode("ascii", errors="replace"), dtype=np.float64,
                                   sep=" ")
    except ValueError:
        values = np.zeros(0)
    if values.size != num_tokens or not np.all(np.isfinite(values)):
        raise InputError("non-numeric or non-finite value", path=str(path), field=_first_bad_line(payload))
    return values.reshape(-1, 4)


def _first_bad_line(payload: bytes) -> str | None:
    """``line N`` of the first value that is not a finite number (the error path only)."""
    for number, line in enumerate(payload.decode("ascii", errors="replace").splitlines(), start=1):
        for token in line.split():
            try:
                finite = np.isfinite(float(token))
            except ValueError:
                finite = False
            if not finite:
                return f"line {number}"
    return None


def read_features(path: PathLike) -> np.ndarray:
    """(n, 2) keypoint pixels of a ``.feat`` file, in COLMAP's pixel convention (+0.5)."""
    return to_colmap_pixels(read_feature_table(path)[:, :2])


def write_features(path: PathLike, pixels: np.ndarray,
                   scales_orientations: np.ndarray | None = None) -> None:
    """Write a ``.feat`` file from (n, 2) COLMAP-convention pixels (-0.5 on the way out).
    Without ``scales_orientations`` each row gets scale 1 and orientation 0, as OpenMVG's own
    external-features demo writes."""
    pixels = np.asarray(pixels, dtype=np.float64).reshape(-1, 2)
    table = np.empty((pixels.shape[0], 4))
    table[:, :2] = to_openmvg_pixels(pixels)
    if scales_orientations is None:
        table[:, 2], table[:, 3] = 1.0, 0.0
    else:
        table[:, 2:] = np.asarray(scales_orientations, dtype=np.float64).reshape(-1, 2)
    if not np.all(np.isfinite(table)):
        raise InputError("non-finite keypoint", path=str(path))
    # Lossless and compact: values that are float32 numbers (every keypoint that came from a
    # detector or a COLMAP database, scale 1, orientation 0) keep %.9g, which is exact for
    # float32; others (e.g. re-projected through a converted camera model) get %.12g:
    # 8 decimals on a 4-digit pixel, 1e-8 px, far below the 1e-9 normalized-coordinate
    # round-trip bound (1.4e-6 px at f = 1380), and stable under write -> read -> write.
    # OpenMVG parses either into its float32 features.
    exact32 = table.astype(np.float32).astype(np.float64) == table
    columns = []
    for c in range(4):
        col = np.empty(table.shape[0], dtype=object)
        for mask, fmt in ((exact32[:, c], "%.9g"), (~exact32[:, c], "%.12g")):
            if np.any(mask):
                values = table[mask, c]
                col[mask] = ((fmt + "\n") * values.shape[0] % tuple(values.tolist())).splitlines()
        columns.append(col)
    text = "".join(f"{a} {b} {c} {d}\n" for a, b, c, d in zip(*columns))
    atomic.write_bytes(path, text.encode("ascii"))
