"""Skipping a top-level array of a JSON text unparsed (io/inputs.without_top_level_array): the
rest of the document parses as if the array had been empty, whatever the strings hold."""

from __future__ import annotations

import json

from hypothesis import given, settings
from hypothesis import strategies as st

from rotonly_cli.io.inputs import _array_end, without_top_level_array

_KEY = "structure"
_TEXT = st.text(alphabet=st.sampled_from(list('ab "[]{}:,\\structure')), max_size=12)
_VALUES = st.recursive(st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | _TEXT,
                       lambda inner: st.lists(inner, max_size=4) | st.dictionaries(_TEXT, inner, max_size=4),
                       max_leaves=20)


def _expected(document: dict, text: bytes) -> dict:
    """What the skip promises: the key's array emptied, unless the text holds a backslash
    (then nothing is changed) or the key's value is not an array."""
    if b"\\" in text or not isinstance(document.get(_KEY), list):
        return document
    return {**document, _KEY: []}


@settings(max_examples=300, deadline=None)
@given(document=st.dictionaries(_TEXT, _VALUES, max_size=5), array=st.lists(_VALUES, max_size=5),
       with_key=st.booleans(), indent=st.sampled_from([None, 0, 4]))
def test_skipping_keeps_the_rest_of_any_document(document, array, with_key, indent):
    if with_key:
        document = {**document, _KEY: array}
    text = json.dumps(document, indent=indent).encode()
    assert json.loads(without_top_level_array(text, _KEY)) == _expected(document, text)


def test_only_the_top_level_member_is_skipped():
    document = {"views": [{"name": "structure", "structure": [1, 2]}], "label": "structure",
                "structure": [{"x": "]]]", "y": [[["{"]]]}], "control_points": [{"key": 1}]}
    text = json.dumps(document).encode()
    out = without_top_level_array(text, _KEY)
    assert json.loads(out) == {**document, "structure": []}
    assert len(out) == len(text) - len(json.dumps(document["structure"])) + 2


def test_a_value_that_is_not_an_array_or_an_unclosed_array_is_left_alone():
    for text in (b'{"structure": {"a": [1]}, "b": 2}', b'{"structure": 3}', b'{"structure": [1, [2]'):
        assert without_top_level_array(text, _KEY) == text


def test_array_end_carries_the_string_and_depth_state_across_blocks(monkeypatch):
    import rotonly_cli.io.inputs as inputs

    text = b'{"s": [' + b'{"a": "]", "b": [1, [2, "["]]}, ' * 50 + b'[]], "t": 1}'
    start = text.index(b"[")
    whole = _array_end(text, start)
    monkeypatch.setattr(inputs, "_SKIP_BLOCK", 7)  # blocks that cut strings and arrays
    assert _array_end(text, start) == whole == text.index(b', "t"')
