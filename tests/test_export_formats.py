"""`rsra export`'s formats are a registry (daq.analysis.export_formats.EXPORT_FORMATS): a
format registered in a test is one class and one entry — its option, its help, its output
checked against the inputs, its staged file — and the command names none."""
import json

import pytest

from rsra.daq.analysis.export import ExportError
from rsra.daq.analysis.export_formats import EXPORT_FORMATS, ExportFormat, ExportJob
from rsra.daq.cli import main

RECORDS = [{"key": "hub_loads", "t": 1.0, "seq": 0}, {"key": "channels", "t": 1.0, "seq": 0},
           {"key": "hub_loads", "t": 1.5, "seq": 1}]


class KeyCsv(ExportFormat):
    """A toy format: one CSV line per record, its key and time."""

    title = "a CSV of the records' keys and times"
    help = "write the records' keys and times as CSV"
    description = "--csv FILE: one line per record, key and time."

    def write(self, job: ExportJob) -> list[str]:
        assert self.out is not None and job.records is not None
        n = 0
        self.out.write(b"key,t\n")
        for key, payload in job.records():
            if payload.get("t") is None:
                raise ExportError(f"{job.source}: a {key} record without a time; fix: give "
                                  "records with times")
            self.out.write(f"{key},{payload['t']}\n".encode())
            n += 1
        return [f"{self.target}: {n} records"]


@pytest.fixture
def results(tmp_path):
    p = tmp_path / "RESULTS.jsonl"
    p.write_text("".join(json.dumps(r) + "\n" for r in RECORDS))
    return p


@pytest.fixture
def csv_format(monkeypatch):
    monkeypatch.setitem(EXPORT_FORMATS, "csv", KeyCsv)


def test_a_registered_format_is_an_option_that_writes_its_file(csv_format, results, tmp_path,
                                                                capsys):
    out = tmp_path / "keys.csv"
    assert main(["export", str(results), "--csv", str(out)]) == 0
    assert out.read_text() == "key,t\nhub_loads,1.0\nchannels,1.0\nhub_loads,1.5\n"
    assert capsys.readouterr().out == f"{out}: 3 records\n"
    with pytest.raises(SystemExit):
        main(["export", "--help"])
    text = capsys.readouterr().out
    assert "--csv FILE" in text and "keys and times as CSV" in text
    assert main(["export", str(results)]) == 2  # the fix names it among the others
    assert "give --dbc FILE, --mcap FILE, --parquet DIR or --csv FILE" in capsys.readouterr().err
    assert main(["export", "--csv", str(out)]) == 2  # a telemetry format without telemetry
    assert "--mcap, --parquet and --csv need the telemetry" in capsys.readouterr().err


def test_a_registered_format_is_checked_against_the_inputs_and_staged(csv_format, results,
                                                                      tmp_path, capsys):
    before = results.read_bytes()
    assert main(["export", str(results), "--csv", str(results)]) == 2  # never onto its input
    assert "--csv" in capsys.readouterr().err and results.read_bytes() == before
    # a format that fails leaves nothing, the other formats of the run included
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"key": "hub_loads", "seq": 0}\n')
    dbc, csv = tmp_path / "bus.dbc", tmp_path / "bad.csv"
    assert main(["export", str(bad), "--dbc", str(dbc), "--csv", str(csv)]) == 2
    assert "without a time; fix:" in capsys.readouterr().err
    assert not dbc.exists() and not csv.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["RESULTS.jsonl", "bad.jsonl"]


def test_without_its_entry_the_option_does_not_exist(results, tmp_path, capsys):
    assert "csv" not in EXPORT_FORMATS
    with pytest.raises(SystemExit) as e:
        main(["export", str(results), "--csv", str(tmp_path / "k.csv")])
    assert e.value.code == 2 and "unrecognized arguments: --csv" in capsys.readouterr().err
