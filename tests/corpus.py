"""The bad-input corpus of issue 21, built from the bundled fixtures (tests/test_bad_inputs.py
runs it): every kind of broken input, destination and workspace rotonly must answer with one
line naming the file and the field, exit 2 (bad input or usage), nothing written, inputs
byte-identical, no traceback.

A case is a name, a builder and what the error line must hold. The builder makes the case's
files in its folder ``root`` (copies of the fixtures, then broken) and returns the command
line; ``bases`` holds what several cases share (a COLMAP model and a workspace written by
one `rotonly run` of the 4-image fixture). OUT is always ``root/new1/new2/OUT``: a case that
leaves ``new1`` behind made folders for a bad input.
"""

from __future__ import annotations

from corpus_inputs import DB_CASES, FILE_CASES, HJ4_DB, MVG_CASES, SPECIAL_CASES, Case
from corpus_models import DESTINATION_CASES, GT_CASES, MODEL_CASES, USAGE_CASES, WS_CASES

__all__ = ["CASES", "HJ4_DB", "Case"]

CASES: list[Case] = [*DB_CASES, *FILE_CASES, *SPECIAL_CASES, *MVG_CASES, *GT_CASES, *MODEL_CASES, *WS_CASES,
                     *DESTINATION_CASES, *USAGE_CASES]
