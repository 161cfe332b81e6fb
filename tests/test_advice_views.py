"""The advice sentence of a filter-error window (estimator.flight_advice.advice_summary) where
an engineer reads it besides the log and the report: `rsra angles show` of a recording and
the angles table of the Parquet export (a string column beside the figures)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from rsra.config.rig import load_config
from rsra.daq.analysis.export import ADVICE_TEXT, declared_columns, flatten, vector_names
from rsra.daq.cli import main
from rsra.estimator.flight_advice import advice_summary

ADVICE = {"determined": 2, "next": 0.74, "n_scored": 899,
          "accelerometers": [{"name": "deck_aft_right", "determined": 2, "gain": 0,
                              "next": 0.88}],
          "manoeuvres": [{"axis": "Y", "rms": 3000.0, "determined": 3, "gain": 1,
                          "next": 1.41}],
          "window": {"extra_s": 1.57, "gain": 1},
          "best": {"kind": "manoeuvre", "name": "Y", "gain": 1, "next": 1.41}}


@pytest.fixture(scope="module")
def cfg():
    return load_config()


def _record(names, seq: int, t: float, accepted: bool, advice=None) -> dict:
    return {"mode": "filter_error", "content": "vibration", "accepted": accepted,
            "reason": None if accepted else "not_identifiable", "names": names,
            "alpha": [0.001] * len(names),
            "P": (np.eye(len(names)) * np.radians(0.5) ** 2).tolist(),
            "determined": 11, "applies_from_seq": seq, "t": t, "advice": advice}


def test_the_parquet_angles_table_has_the_advice_sentence(cfg):
    """A declared string column `advice_text`, equal to the log's sentence (with the count
    of the record's angles), null for a record without advice. Break-checked: without the
    row's value the first assertion fails; without the declaration the second."""
    names = list(cfg.rig_model().geometry.angle_names)
    row = flatten("angles", _record(names, 10, 1.0, True, ADVICE), vector_names(cfg))
    assert row[ADVICE_TEXT] == advice_summary(ADVICE, len(names))
    assert row[ADVICE_TEXT].startswith("This window determines 2 of 14 directions.")
    assert (ADVICE_TEXT, "string") in declared_columns("angles", vector_names(cfg))
    assert flatten("angles", _record(names, 10, 1.0, True), vector_names(cfg))[ADVICE_TEXT] \
        is None


def test_angles_show_of_a_recording_says_the_latest_advice(cfg, tmp_path, capsys):
    """`rsra angles show REC` prints the latest advice (a later, not applied window's) in
    the same sentence, and --json carries it under source.advice. Break-checked: printing
    the last applied record's advice instead fails the sentence check (3 vs 2 determined)."""
    names = list(cfg.rig_model().geometry.angle_names)
    later = {**ADVICE, "determined": 2}
    recs = [_record(names, 10, 1.0, True, {**ADVICE, "determined": 3}),
            _record(names, 20, 2.0, False, later), _record(names, 30, 3.0, False)]
    (tmp_path / "angles.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    assert main(["angles", "show", str(tmp_path)]) == 0
    out = " ".join(capsys.readouterr().out.split())
    assert f"advice (record 2, the latest filter-error window with advice): " \
        f"{advice_summary(later, 14)}" in out
    assert main(["angles", "show", str(tmp_path), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["source"]["advice"] == {"index": 2, "t": 2.0,
                                     "sentence": advice_summary(later, 14)}
    (tmp_path / "angles.jsonl").write_text(json.dumps(recs[2] | {"accepted": True}) + "\n")
    assert main(["angles", "show", str(tmp_path), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["source"]["advice"] is None
