"""One mapping from the names of `rotonly run`'s options to the RunOptions fields they set: the
CLI's long options (``--ransac-max-error`` is ``ransac_max_error``; click passes them under these
names) and the keywords of the Python API (``rotonly_cli.run``) are the same names, and both build
their RunOptions with :func:`with_settings`."""

from __future__ import annotations

from dataclasses import replace

from rotonly_cli.errors import InputError
from rotonly_cli.options import RunOptions
from rotonly_cli.options.common import CONSENSUS_MODES, INTRINSICS_MODES, Consensus, Intrinsics, Reestimate
from rotonly_cli.options.inputs import AUTO_AGREEMENT_MIN_EDGES, FAST_CONSENSUS_AGREEMENT

#: name -> (the part of RunOptions it sets: "" for RunOptions itself, else its field holding
#: that stage's options; the field)
SETTINGS = {
    "matches_dir": ("", "matches_dir"),
    "matches": ("", "matches_file"),
    "image_path": ("", "image_path"),
    "gt": ("", "gt"),
    "grrm": ("", "grrm"),
    "jobs": ("", "jobs"),
    "cluster": ("", "cluster"),
    "progress": ("", "progress"),
    "max_memory": ("", "max_memory_gb"),
    "min_inliers": ("load", "min_inliers"),
    "reestimate": ("load", "reestimate"),
    "ransac_max_error": ("load", "ransac_max_error_px"),
    "seed": ("load", "seed"),
    "consensus": ("load", "consensus"),
    "max_residual_deg": ("average", "max_residual_deg"),
    "intrinsics": ("intrinsics", "mode"),
}


#: the LoadOptions fields each --consensus mode sets
CONSENSUS_FIELDS = {
    Consensus.AUTO: {"consensus_agreement": FAST_CONSENSUS_AGREEMENT, "agreement_min_edges": AUTO_AGREEMENT_MIN_EDGES},
    Consensus.FULL: {"consensus_agreement": None},
    Consensus.FAST: {"consensus_agreement": FAST_CONSENSUS_AGREEMENT, "agreement_min_edges": 0},
}

#: the fields that hold a path, as text
PATHS = ("matches_dir", "matches_file", "image_path", "gt")


def _fields(field: str, value) -> dict:
    """The fields a setting sets, as they hold its ``value``: paths as text, the choices as
    their StrEnum (a mode that is not one stays as given, for the options' validate() to
    name); ``consensus``, a mode that sets several fields, those of CONSENSUS_FIELDS (a name
    that is not one refused here: the fields are numbers)."""
    if field == "consensus":
        if value not in CONSENSUS_MODES:
            raise InputError(f"{value!r}: must be one of {', '.join(CONSENSUS_MODES)}", field="consensus")
        return CONSENSUS_FIELDS[Consensus(value)]
    return {field: _value(field, value)}


def _value(field: str, value):
    """``value`` as the field holds it (:func:`_fields`)."""
    if field in PATHS:
        return str(value)
    if field == "reestimate":
        return Reestimate(value)
    if field == "mode":
        return Intrinsics(value) if value in INTRINSICS_MODES else value
    return value


def with_settings(options: RunOptions, settings: dict) -> RunOptions:
    """``options`` with the ``settings`` ({name of :data:`SETTINGS`: value}) applied; a None
    value leaves its field as it is in ``options``."""
    changes: dict[str, dict] = {}
    for name, value in settings.items():
        if value is not None:
            part, field = SETTINGS[name]
            changes.setdefault(part, {}).update(_fields(field, value))
    parts = {part: replace(getattr(options, part), **fields) for part, fields in changes.items() if part}
    return replace(options, **changes.get("", {}), **parts)
