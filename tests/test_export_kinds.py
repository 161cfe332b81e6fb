"""Every kind of recording exports to Parquet and MCAP: ground, flight, flight rig (whose
filter-error runs carry ``load_excursion``: its σ is one number, declared as a list until
it broke the flight rig's export), started with --angles, and faulted."""
from __future__ import annotations

from pathlib import Path

import pyarrow.parquet as pq
import pytest
from helpers_net import free_tcp_port
from mcap.reader import make_reader

from rsra.daq.cli import main

ROOT = Path(__file__).resolve().parents[1]
FLIGHT_RIG = str(ROOT / "config" / "flight-rig.toml")


def _record(folder: Path, *args: str, duration: str = "2") -> Path:
    assert main(["run", "--speed", "max", "--duration", duration, "--record", str(folder),
                 "--zenoh-listen", f"tcp/127.0.0.1:{free_tcp_port()}", *args]) == 0
    return folder


@pytest.fixture(scope="module")
def kinds(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("kinds")
    state = d / "state.json"
    assert main(["angles", "reset", str(state)]) == 0
    return {
        "ground": _record(d / "ground", "--sim", "ground-test"),
        "flight": _record(d / "flight", "--sim", "flight"),
        # long enough for a filter-error run to reach its checks (load_excursion)
        "flight rig": _record(d / "flight_rig", "--config", FLIGHT_RIG, "--sim", "flight",
                              duration="7"),
        "angles": _record(d / "angles", "--sim", "ground-test", "--angles", str(state)),
        "faulted": _record(d / "faulted", "--sim", "ground-test",
                           "--faults", "overrange:cell_C@0.1;drop:accel_1:0.05"),
    }


@pytest.mark.parametrize("kind", ["ground", "flight", "flight rig", "angles", "faulted"])
def test_every_kind_of_recording_exports_to_parquet_and_mcap(kinds, kind, tmp_path):
    rec = kinds[kind]
    pqdir, mcap = tmp_path / "pq", tmp_path / "out.mcap"
    assert main(["export", str(rec), "--parquet", str(pqdir), "--mcap", str(mcap)]) == 0
    tables = {p.stem: pq.read_table(p) for p in pqdir.glob("*.parquet")}
    assert {"hub_loads", "channels", "health"} <= set(tables)
    assert tables["hub_loads"].num_rows > 0
    with open(mcap, "rb") as f:
        topics = {ch.topic for _, ch, _ in make_reader(f).iter_messages()}
    assert any(t.endswith("/hub_loads") for t in topics)
    if kind == "flight rig":  # the record that broke it is there, with its σ columns
        angles = tables["angles"]
        assert any(v is not None for v in angles.column("load_excursion.sigma").to_pylist())
        sig = [c for c in angles.column_names if c.startswith("sigma_deg.")]
        assert len(sig) == 14 and angles.schema.field(sig[0]).metadata[b"unit"] == b"deg"


def test_the_sigma_column_is_the_root_of_the_posterior_variance_in_degrees(kinds, tmp_path):
    import math

    assert main(["export", str(kinds["flight rig"]), "--parquet", str(tmp_path / "pq")]) == 0
    t = pq.read_table(tmp_path / "pq" / "angles.parquet").to_pylist()
    assert t
    for row in t:
        for i, name in enumerate(row["names"]):
            assert row[f"sigma_deg.{name}"] == pytest.approx(
                math.degrees(math.sqrt(row["P"][i][i])), rel=1e-12)


def test_a_value_of_another_type_than_declared_is_left_out_and_named(tmp_path, capsys):
    """A telemetry file from elsewhere whose value does not fit its declared column (a
    scalar where a list is declared) is exported without it, and the command says so —
    instead of the internal error the flight rig's records once gave."""
    import json

    rec = {"key": "innovations", "seq": 1, "t": 1.0, "e": [1.0] * 6, "nis": 2.0}
    src = tmp_path / "results.jsonl"
    src.write_text(json.dumps(rec) + "\n" + json.dumps({**rec, "seq": 2, "nis": [1, 2]}) + "\n")
    assert main(["export", str(src), "--parquet", str(tmp_path / "pq")]) == 0
    t = pq.read_table(tmp_path / "pq" / "innovations.parquet")
    assert t.column("seq").to_pylist() == [1, 2] and t.column("e.X").to_pylist() == [1.0, 1.0]
    assert t.column("nis").to_pylist() == [2.0, None]
    out = capsys.readouterr().out
    assert "left out: nis" in out
