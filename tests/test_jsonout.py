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


def _stdlib_text(obj) -> str:
    return json.dumps(obj, allow_nan=False, separators=(",", ":"))


def test_floats_of_every_magnitude_encode_as_the_stdlib():
    """The orjson path (daq/jsonout.dumpb) keeps its text only where it is the stdlib's:
    random bit patterns (every exponent) and short decimals across the exponent forms."""
    rng = np.random.default_rng(17)
    bits = rng.integers(0, 2**63, size=40_000, dtype=np.int64).view(np.float64)
    x = bits[np.isfinite(bits)]
    dec = np.round(rng.standard_normal(20_000) * 1e3, 3) * 10.0 ** rng.integers(-12, 22, 20_000)
    edges = [1e-4, 9.999999999999999e-05, 1e-5, 1.5e-5, 1e-10, 1e16, 9999999999999998.0,
             1e17, 5e-324, -0.0, 0.0, 1.7976931348623157e308, 123.456e-7]
    for vals in (x.tolist(), (-x).tolist(), dec.tolist(), edges):
        assert dumps(vals) == _stdlib_text(vals)
        assert dumps(np.array(vals)) == _stdlib_text(vals)
        for v in vals[:200]:
            assert dumps({"v": v}) == _stdlib_text({"v": v})


def test_strings_keys_and_types_orjson_writes_otherwise_take_the_stdlib_path():
    import dataclasses
    import enum

    class Level(enum.IntEnum):
        HIGH = 2

    class Name(str):
        pass

    @dataclasses.dataclass
    class Rec:
        a: int = 1

    for obj in ({"s": "é"}, {"s": "\x7f"}, {"s": "a\nb\t\x01\"\\/"}, {"s": "\u2028"},
                {1: 2, "k": None}, {"n": 2**70}, {"n": -2**63 - 1}, {"e": Level.HIGH},
                {"n": Name("x")}, {"t": (1, 2.5)}, {"deep": [[[[1.0e-7]]]]}):
        assert dumps(obj) == _stdlib_text(sanitise(obj))
    with pytest.raises(TypeError):
        dumps({"r": Rec()})  # the stdlib refuses a dataclass: so does dumps
    with pytest.raises(TypeError):
        dumps({"c": np.array([1j])})
