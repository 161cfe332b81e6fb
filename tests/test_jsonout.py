"""daq/jsonout.dumps: the fast path (encoder with numpy conversions, no tree copy) gives
text for text what the strict path ``json.dumps(sanitise(obj))`` gives, for the payload
shapes the service publishes and for random trees with non-finite values and numpy types."""
from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rsra.daq.jsonout import dumps, sanitise


def reference(obj) -> str:
    return json.dumps(sanitise(obj), allow_nan=False, separators=(",", ":"))


def test_a_hub_loads_and_a_channels_record_encode_as_the_strict_path():
    rng = np.random.default_rng(3)
    hub = {"seq": np.int64(12), "sync": 12, "t": 0.06, "frame": "body",
           "H": rng.standard_normal(6) * 1e4, "H_static": None, "omega": np.float32(19.4),
           "flags": ["lost"]}
    ch = {"seq": 3, "t": 1.0 / 3, "T": rng.standard_normal(7), "accel": rng.random((2, 3)),
          "I": np.array([np.nan, 1.0, np.inf, -np.inf, 0.0, -0.0]), "omega": float("nan"),
          "azimuth": None, "known_H": None, "drive": np.array([1, 2]), "status": {"A": 0},
          "ok": np.bool_(True), "e": np.float64("nan")}
    for rec in (hub, ch):
        assert dumps(rec) == reference(rec)
    assert '"I":[null,1.0,null,null,0.0,-0.0]' in dumps(ch)
    assert '"omega":null' in dumps(ch) and '"e":null' in dumps(ch)


def test_an_unencodable_object_is_still_refused():
    with pytest.raises(TypeError):
        dumps({"x": object()})


finite = st.floats(allow_nan=True, allow_infinity=True, width=64)
leaves = st.one_of(
    st.none(), st.booleans(), st.integers(-10**6, 10**6), finite, st.text(max_size=4),
    finite.map(np.float64), st.floats(width=32).map(np.float32),
    st.integers(-1000, 1000).map(np.int32), st.booleans().map(np.bool_),
    st.lists(finite, max_size=5).map(lambda v: np.array(v, float)),
    st.lists(st.integers(-5, 5), max_size=5).map(lambda v: np.array(v, np.int64)))
trees = st.recursive(leaves, lambda c: st.one_of(
    st.lists(c, max_size=4), st.tuples(c, c), st.dictionaries(st.text(max_size=3), c,
                                                               max_size=4)), max_leaves=20)


@settings(max_examples=300, deadline=None)
@given(trees)
def test_random_trees_encode_as_the_strict_path(obj):
    assert dumps(obj) == reference(obj)
