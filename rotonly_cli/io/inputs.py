"""How every input file is opened and checked before its content is believed.

* Only regular files are read: a named pipe, a device or a socket is refused from its
  ``stat`` before it is opened (opening a pipe for reading blocks until a writer comes), and
  the file is opened non-blocking and checked again, so a swap in between changes nothing.
* JSON: nesting deeper than :data:`MAX_JSON_DEPTH` is refused before parsing, numbers longer
  than :data:`MAX_NUMBER_CHARS` characters are not converted (they become an
  :class:`Oversized` that every typed field refuses with its name), ``NaN`` / ``Infinity``
  become floats that every number field refuses as not finite.
* Cameras: :func:`check_camera` is the one rule for intrinsics (finite values, focal lengths
  > 0, a principal point inside an image of positive size), whatever the format.

Every error is an :class:`InputError` naming the file and the field.
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import stat
from collections.abc import Sequence
from typing import Any, BinaryIO

import numpy as np

from rotonly_cli.errors import InputError

PathLike = str | os.PathLike

#: deepest JSON nesting read (OpenMVG's sfm_data.json is 8 deep, rotonly's own files less)
MAX_JSON_DEPTH = 64
#: longest JSON number converted (uint64: 20 digits; a double's shortest form: 24 characters)
MAX_NUMBER_CHARS = 40

_KINDS = ((stat.S_ISFIFO, "a named pipe"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISSOCK, "a socket"))


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def check_regular_file(path: PathLike, field: str | None = None) -> os.stat_result:
    """``stat`` of ``path`` if it is a regular file (symbolic links followed); InputError
    otherwise. Nothing is opened."""
    try:
        info = os.stat(path)
    except FileNotFoundError:
        raise InputError("file not found", path=str(path), field=field) from None
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", path=str(path), field=field) from None
    if stat.S_ISDIR(info.st_mode):
        raise InputError("is a folder, expected a file", path=str(path), field=field)
    if not stat.S_ISREG(info.st_mode):
        raise InputError(f"is {_kind(info.st_mode)}, expected a regular file", path=str(path), field=field)
    return info


def open_input(path: PathLike, field: str | None = None) -> BinaryIO:
    """``path`` opened for reading (binary) if it is a regular file; InputError otherwise."""
    check_regular_file(path, field)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", path=str(path), field=field) from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):  # replaced since the stat above
            raise InputError(f"is {_kind(info.st_mode)}, expected a regular file", path=str(path), field=field)
        fcntl.fcntl(fd, fcntl.F_SETFL, fcntl.fcntl(fd, fcntl.F_GETFL) & ~os.O_NONBLOCK)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_bytes(path: PathLike, field: str | None = None) -> bytes:
    """The whole content of a regular file; InputError if it cannot be read."""
    with open_input(path, field) as stream:
        try:
            return stream.read()
        except OSError as exc:
            raise InputError(f"cannot read: {exc.strerror}", path=str(path), field=field) from None


# ============================================================================ JSON

class Oversized:
    """A JSON number too long to be converted (more than MAX_NUMBER_CHARS characters)."""

    def __init__(self, text: str):
        self.length = len(text)

    def __repr__(self) -> str:
        return f"a number of {self.length} characters"


def _parse_int(text: str) -> int | Oversized:
    return int(text) if len(text) <= MAX_NUMBER_CHARS else Oversized(text)


def _parse_float(text: str) -> float | Oversized:
    return float(text) if len(text) <= MAX_NUMBER_CHARS else Oversized(text)


#: every byte but the ones that open or close a JSON string, array or object
_NOT_STRUCTURAL = bytes(sorted(set(range(256)) - set(b'"[]{}')))


def _brackets_outside_strings(payload: bytes) -> bytes:
    """The brackets of a JSON text (or of a piece that starts outside a string) that are not
    inside a string, in order. In C loops: escapes removed, every byte but quotes and brackets
    dropped, the strings left (quote, brackets, quote) removed."""
    if b"\\" in payload:
        payload = re.sub(rb"\\.", b"", payload, flags=re.DOTALL)
    structure = payload.translate(None, _NOT_STRUCTURAL).replace(b'""', b"")
    if b'"' in structure:  # strings that hold brackets
        structure = re.sub(rb'"[^"]*"?', b"", structure)
    return structure


def json_depth(payload: bytes) -> int:
    """The deepest array/object nesting of a JSON text, without parsing it (brackets inside
    strings do not count): a running sum over :func:`_brackets_outside_strings`."""
    codes = np.frombuffer(_brackets_outside_strings(payload), dtype=np.uint8)
    if codes.size == 0:
        return 0
    steps = np.where((codes == ord("[")) | (codes == ord("{")), 1, -1).astype(np.int32)
    return int(np.cumsum(steps).max())


def load_json(path: PathLike, skip_member: str | None = None) -> Any:
    """The parsed JSON document of a regular file, with the bounds of the module docstring.
    ``skip_member``: a member of the top-level object read as ``[]`` instead of parsed
    (:func:`without_top_level_array`)."""
    payload = read_bytes(path)
    if skip_member is not None:
        payload = without_top_level_array(payload, skip_member)
    return parse_json(payload, path)


#: bytes scanned at a time when an array is skipped (the bool mask of a block is as large)
_SKIP_BLOCK = 1 << 26
_BRACKET_STEP = np.zeros(256, dtype=np.int8)
_BRACKET_STEP[[ord("["), ord("{")]] = 1
_BRACKET_STEP[[ord("]"), ord("}")]] = -1
_QUOTE_OR_BRACKET = np.zeros(256, dtype=bool)
_QUOTE_OR_BRACKET[list(b'"[]{}')] = True
_NAME_SEPARATOR = re.compile(rb"\s*:\s*")


def _array_end(payload: bytes, start: int) -> int:
    """The index just past the array whose ``[`` is at ``start``; -1 if it is not closed. A
    quote toggles "inside a string" (the text holds no escapes); brackets inside strings do
    not count. numpy over blocks of the bytes, the string parity and the depth carried."""
    parity, depth = 0, 0
    for offset in range(start, len(payload), _SKIP_BLOCK):
        codes = np.frombuffer(payload, dtype=np.uint8, count=min(_SKIP_BLOCK, len(payload) - offset), offset=offset)
        where = np.flatnonzero(_QUOTE_OR_BRACKET[codes])
        chars = codes[where]
        quotes = chars == ord('"')
        inside = (parity + np.cumsum(quotes)) % 2 == 1  # a bracket's own parity is the one before it
        steps = np.where(quotes | inside, 0, _BRACKET_STEP[chars]).astype(np.int64)
        depths = depth + np.cumsum(steps)
        closed = np.flatnonzero(depths == 0)
        if closed.size:
            return offset + int(where[closed[0]]) + 1
        parity = (parity + int(np.count_nonzero(quotes))) % 2
        depth = int(depths[-1]) if depths.size else depth
    return -1


def without_top_level_array(payload: bytes, key: str) -> bytes:
    """``payload`` (a JSON object) with the array value of its top-level member ``key``
    replaced by ``[]``, found without parsing it: a reader of poses needs nothing of OpenMVG's
    ``structure``, which is most of the file (a simulated 1000-view collection's ground truth:
    1 GB, parsed in 40 s with a 3.7 GB peak and 2.0 GB held; skipped, 6 s and 1.2 GB, the
    bytes read). Returned unchanged when the text holds
    a backslash (escaped quotes would need a real parser), when ``key`` is not a member of
    the top-level object, or when its value is not an array."""
    if b"\\" in payload:
        return payload
    needle = json.dumps(key).encode()
    found, scanned, depth = payload.find(needle), 0, 0
    while found >= 0:
        # without backslashes every quote opens or closes a string: the needle's first quote
        # opens one (closing one it would make the text malformed), so the text from one
        # occurrence to the next starts outside a string, and its brackets add to the depth
        brackets = _brackets_outside_strings(payload[scanned:found])
        depth += brackets.count(b"[") + brackets.count(b"{") - brackets.count(b"]") - brackets.count(b"}")
        scanned = found
        after = _NAME_SEPARATOR.match(payload, found + len(needle))
        if depth == 1 and after is not None:  # a member of the top-level object, not a value
            value = after.end()
            end = _array_end(payload, value) if payload[value:value + 1] == b"[" else -1
            return payload if end < 0 else payload[:value] + b"[]" + payload[end:]
        found = payload.find(needle, found + 1)
    return payload


def parse_json(payload: bytes | str, path: PathLike, field: str | None = None) -> Any:
    """``payload`` parsed with the bounds of the module docstring; errors name ``path``
    (and ``field``: where in the file the JSON text was)."""
    if isinstance(payload, str):
        payload = payload.encode("utf-8", errors="surrogatepass")
    depth = json_depth(payload)
    if depth > MAX_JSON_DEPTH:
        raise InputError(f"JSON nested {depth} levels deep (at most {MAX_JSON_DEPTH} are read)", path=str(path),
                         field=field)
    try:
        return json.loads(payload, parse_int=_parse_int, parse_float=_parse_float, parse_constant=float)
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise InputError(f"malformed JSON ({error})", path=str(path), field=field) from None
    except RecursionError:  # a nesting within MAX_JSON_DEPTH never gets here
        raise InputError("JSON nested too deeply", path=str(path), field=field) from None


# ============================================================================ cameras

def check_camera(path: PathLike | None, field: str, width, height, focal_lengths: Sequence[float],
                 principal_point: Sequence[float], params: Sequence[float] = ()) -> None:
    """InputError naming ``path`` and ``field`` unless: ``width`` and ``height`` are
    integers > 0, every value of ``params`` (all of the camera's parameters) is finite,
    every focal length is finite and > 0, and the principal point lies in [0, width] x
    [0, height]."""
    where = None if path is None else str(path)
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
            raise InputError(f"{name} {value!r}: an image size must be a positive integer", path=where, field=field)
    values = np.asarray(params, dtype=np.float64).ravel()
    if not np.all(np.isfinite(values)):
        bad = int(np.flatnonzero(~np.isfinite(values))[0])
        raise InputError(f"parameter {bad} is {values[bad]}: not finite", path=where, field=field)
    for focal in focal_lengths:
        if not np.isfinite(focal) or focal <= 0:
            raise InputError(f"focal length {focal}: must be finite and > 0", path=where, field=field)
    cx, cy = (float(v) for v in principal_point)
    if not (np.isfinite(cx) and np.isfinite(cy) and 0 <= cx <= width and 0 <= cy <= height):
        raise InputError(f"principal point ({cx}, {cy}) outside the {width} x {height} image", path=where,
                         field=field)


def check_finite(values: np.ndarray, path: PathLike | None, field: str, what: str = "value") -> None:
    """InputError naming the first non-finite entry of ``values`` (its row for 2-D arrays)."""
    values = np.asarray(values)
    if values.size and not np.all(np.isfinite(values)):
        index = np.argwhere(~np.isfinite(values))[0]
        position = f"row {int(index[0])}" if values.ndim > 1 else f"entry {int(index[0])}"
        raise InputError(f"{what} at {position} is {values[tuple(index)]}: not finite",
                         path=None if path is None else str(path), field=field)
