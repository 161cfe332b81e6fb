"""The user documentation stays honest (docs/configuration.md, docs/cli.md, docs/telemetry.md).

* every key of the packaged rig TOML, and every key of the rig schema (config/rigfile.py, the
  pydantic models the loader validates with), is documented in its section of configuration.md;
* every `rsra` command, and every option, positional argument and choice of its argparse
  parser, appears in that command's section of cli.md;
* every Zenoh key and every payload field the service publishes — found by running a short
  lock-step service on the simulator, with a recording and an injected fault so that the
  optional fields show — appears in that key's section of telemetry.md, and so does every
  flag, rejection reason, mode, content and node state the code can produce;
* the Python subscriber in telemetry.md is extracted and run, in another process, against a
  live publisher; what it prints is checked against what was published;
* every citation in the code (`model §6`, `docs/bus.md §3 "Boot and supervision"`,
  `reliability.md "Soak"`) names a numbered section, heading or page that exists in docs/, and
  every relative link of every page resolves.
"""
from __future__ import annotations

import argparse
import ast
import copy
import json
import re
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from rsra.config.rig import CONTENTS, ROLES, config_dir, load_config, parse_config
from rsra.config.rigfile import schema_keys

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def _read(name: str) -> str:
    return (DOCS / name).read_text(encoding="utf-8")


def section(text: str, heading: str) -> str:
    """The body of the first Markdown heading whose title contains `heading`, up to the next
    heading of the same or a higher level."""
    lines = text.splitlines()
    for i, line in enumerate(lines):
        m = re.match(r"^(#+)\s+(.*)$", line)
        if m and heading in m.group(2):
            level = len(m.group(1))
            body = []
            for nxt in lines[i + 1:]:
                m2 = re.match(r"^(#+)\s", nxt)
                if m2 and len(m2.group(1)) <= level:
                    break
                body.append(nxt)
            return "\n".join(body)
    raise AssertionError(f"no heading containing {heading!r}")


def code_names(text: str) -> set[str]:
    """Everything written as `code` in a Markdown text."""
    return set(re.findall(r"`([^`\n]+)`", text))


# ------------------------------------------------------------------------------------------
# configuration.md

def _config_section(doc: str, table: str) -> str:
    for h in (f"`[[{table}]]`", f"`[{table}]`"):
        try:
            return section(doc, h)
        except AssertionError:
            continue
    raise AssertionError(f"configuration.md has no section for [{table}] or [[{table}]]")


def _toml_keys(raw: dict) -> set[tuple[str, str]]:
    """(table, key) of every key of a rig TOML; calibration entries as "<node>.<channel>"."""
    out = set()
    for table, value in raw.items():
        items = value if isinstance(value, list) else [value]
        for item in items:
            assert isinstance(item, dict), table
            for k, v in item.items():
                if table == "calibration":
                    out.add((table, '"<node>.<channel>"'))
                    out.update((table, kk) for kk in v)
                else:
                    out.add((table, k))
    return out


def _full_raw() -> dict:
    """The packaged rig with every optional section and every list form in use."""
    raw = copy.deepcopy(load_config().raw)
    raw["nodes"].append({"name": "drive", "role": "drive_load", "node_id": 0x51,
                         "eds": "eds/drive_load.eds", "required": False})
    raw["external_loads"] = [{"name": "drive_torque", "node": "drive", "sigma": 5.0,
                              "wrench_per_unit": [0.0, 0.0, 0.0, 0.0, 0.0, 1.0]}]
    raw["calibration"] = {"cell_A.force": {"gain": 1.001, "offset": 2.5}}
    raw["filter"]["process_noise_psd"] = [1e6, 1e6, 1e6, 1e5, 1e5, 1e5]
    raw["identification"]["initial_angles_deg"] = [0.5] * 14
    raw["identification"]["parameters"] = ["delta_A", "theta_A"]
    return raw


def test_every_config_key_is_documented_in_its_section():
    doc = _read("configuration.md")
    packaged = load_config().raw
    parse_config(copy.deepcopy(_full_raw()), base_dir=config_dir())  # a valid rig
    known = schema_keys()
    # the schema knows every key the files hold (and the defaulted ones besides)
    assert _toml_keys(packaged) | _toml_keys(_full_raw()) <= known and len(known) > 80
    wanted = known
    missing = []
    for table, key in sorted(wanted):
        body = _config_section(doc, table)
        if key not in code_names(body):
            missing.append(f"[{table}] {key}")
    assert not missing, "undocumented config keys: " + ", ".join(missing)


def test_every_key_name_the_loader_knows_is_documented():
    """Every key name of the rig schema (config.rigfile), also those of tables the packaged
    rig leaves out, appears in configuration.md."""
    names = {key for _, key in schema_keys()} | {table for table, _ in schema_keys()}
    assert {"sample_rate_hz", "state_file", "zenoh_config", "alpha0_deg"} <= names
    documented = code_names(_read("configuration.md"))
    tables = {n for n in names if f"[{n}]" in documented or f"[[{n}]]" in documented}
    missing = sorted(n for n in names - tables if n not in documented)
    assert not missing, f"config keys of config/rigfile.py not documented: {missing}"


def test_config_doc_names_every_role_choice_and_channel():
    doc = _read("configuration.md")
    names = code_names(doc)
    assert set(ROLES) <= {n.strip('"') for n in names}
    assert {f'"{c}"' for c in CONTENTS} <= names
    from rsra.config.devices import DEVICE_PROFILES

    for role, profile in DEVICE_PROFILES.items():
        for channel in profile.names:
            assert f"`{channel}`" in doc, (role, channel)
    for eds in sorted((config_dir() / "eds").glob("*.eds")):
        assert f"`{eds.name}`" in doc, eds.name


# ------------------------------------------------------------------------------------------
# cli.md

def _subparsers(p: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for a in p._actions:
        if isinstance(a, argparse._SubParsersAction):
            return dict(a.choices)
    return {}


def _mentions(text: str, word: str) -> bool:
    return re.search(rf"(?<![\w-]){re.escape(word)}(?![\w-])", text) is not None


def _check_parser(p: argparse.ArgumentParser, body: str, where: str, problems: list[str]) -> None:
    for a in p._actions:
        if isinstance(a, argparse._HelpAction):
            continue
        if isinstance(a, argparse._SubParsersAction):
            for name, sub in a.choices.items():
                if not _mentions(body, name):
                    problems.append(f"{where} {name}")
                _check_parser(sub, body, f"{where} {name}", problems)
            continue
        if a.option_strings:
            for opt in a.option_strings:
                if not _mentions(body, opt):
                    problems.append(f"{where} {opt}")
        else:
            label = a.metavar or a.dest
            if label not in body:
                problems.append(f"{where} positional {label}")
        for choice in a.choices or ():
            if isinstance(a.choices, dict):
                continue
            if not _mentions(body, str(choice)):
                problems.append(f"{where} {a.option_strings or a.dest} choice {choice}")


def test_every_command_and_option_is_in_cli_md():
    from rsra.daq.cli import COMMANDS, build_parser

    doc = _read("cli.md")
    commands = _subparsers(build_parser())
    assert set(commands) == set(COMMANDS)
    problems: list[str] = []
    for name, sub in commands.items():
        try:
            body = section(doc, f"`rsra {name}")
        except AssertionError:
            problems.append(f"no section for rsra {name}")
            continue
        _check_parser(sub, body, f"rsra {name}", problems)
    assert not problems, "missing from docs/cli.md: " + "; ".join(problems)


def test_cli_md_exit_status_table_matches_the_code():
    from rsra.daq.cli import main

    body = section(_read("cli.md"), "Exit status")
    rows = dict(re.findall(r"^\|\s*`(\d+)`\s*\|(.*)\|\s*$", body, re.MULTILINE))
    assert {"0", "1", "2", "130"} <= set(rows)
    assert "usage" in rows["2"] and "configuration" in rows["2"]
    # a configuration error and a usage error are 2, as documented
    assert main(["noise-budget", "--config", str(ROOT / "no-such-rig.toml")]) == 2
    assert main(["run"]) == 2


# ------------------------------------------------------------------------------------------
# telemetry.md: what a short lock-step service really publishes

@pytest.fixture(scope="module")
def published(tmp_path_factory):
    from rsra.daq.jsonout import dumps
    from rsra.daq.runtime.service import Service, ServiceOptions

    cfg = load_config()
    rec = tmp_path_factory.mktemp("docs") / "rec"
    # a recording (recording.* fields) and an over-range on cell A (EMCY, flags)
    svc = Service(cfg, ServiceOptions(sim="ground-test", speed=None, duration=6, zenoh=False,
                                      record=str(rec), faults="overrange:cell_A@2-2.2", seed=3))
    records: list[tuple[str, dict]] = []
    svc.add_sink(lambda k, p: records.append((k, json.loads(dumps(p)))))
    svc.run()
    return records


MAPS = {("health", "nodes"): "<node>", ("channels", "status"): "<cell>"}


def leaf_paths(key: str, obj: dict, prefix: str = "") -> set[str]:
    """Dotted paths of every leaf field; name-keyed maps as <node>/<cell>, list items as []."""
    out = set()
    for k, v in obj.items():
        p = f"{prefix}.{k}" if prefix else k
        if (key, p) in MAPS:
            for item in v.values():
                q = f"{p}.{MAPS[(key, p)]}"
                out |= leaf_paths(key, item, q) if isinstance(item, dict) and item else {q}
        elif isinstance(v, dict) and v:
            out |= leaf_paths(key, v, p)
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
            for item in v:
                out |= leaf_paths(key, item, f"{p}[]")
        else:
            out.add(p)
    return out


def test_the_run_published_every_key(published):
    from rsra.daq.runtime.telemetry import HIGH_RATE_KEYS, LOW_RATE_KEYS

    keys = {k for k, _ in published}
    assert keys == set(HIGH_RATE_KEYS + LOW_RATE_KEYS)


def test_every_key_and_payload_field_is_in_telemetry_md(published):
    from rsra.daq.runtime.telemetry import STATE_KEYS

    doc = _read("telemetry.md")
    key_table = doc.split("\n## ")[0]  # the introduction, with its table of keys
    problems = []
    fields: dict[str, set[str]] = {}
    for k, payload in published:
        fields.setdefault(k, set()).update(leaf_paths(k, payload))
    for k, paths in fields.items():
        if f"`<prefix>/{k}`" not in key_table:
            problems.append(f"key {k} not in the key table")
        body = section(doc, f"`<prefix>/{k}`")
        for p in sorted(paths):
            if f"`{p}`" not in body:
                problems.append(f"{k}: field {p}")
    for k in [f"state/{s}" for s in STATE_KEYS] + ["alive"]:
        if f"`<prefix>/{k}`" not in key_table:
            problems.append(f"key {k} not in the key table")
    state = section(doc, "`<prefix>/state/angles`")
    assert all(f"`<prefix>/state/{s}`" in doc for s in STATE_KEYS)
    assert "<removed>" in state
    # the optional fields this run had: recording, EMCY history, the over-range flag
    assert "recording.dir" in fields["health"] and "nodes.<node>.emcy[].code" in fields["health"]
    flags = {f for _, p in published if _ == "hub_loads" for f in p["flags"]}
    assert "overrange:A" in flags
    assert not problems, "missing from docs/telemetry.md: " + "; ".join(problems)


def test_every_flag_reason_mode_and_state_is_in_telemetry_md(published):
    from rsra.daq.bus.master import NMT_STATE_NAMES
    from rsra.estimator.filters import INVALID, LOST_BEFORE, PREDICT_ONLY, ROTOR_STOPPED
    from rsra.estimator.posterior import MODES, REASONS

    doc = _read("telemetry.md")
    hub = code_names(section(doc, "`<prefix>/hub_loads`"))
    flags = {f for k, p in published if k == "hub_loads" for f in p["flags"]}
    from rsra.estimator.angle_uncertainty import ANGLES_UNCERTAIN
    from rsra.estimator.transient import TRANSIENT

    vocabulary = {PREDICT_ONLY, INVALID, LOST_BEFORE, ROTOR_STOPPED, TRANSIENT, ANGLES_UNCERTAIN,
                  "missing:<node>", "overrange:<cell>", "fault:<cell>"}
    for f in flags:  # every flag seen belongs to the documented vocabulary
        kind = f.split(":")[0]
        assert f in vocabulary or any(v.startswith(kind + ":") for v in vocabulary), f
    assert vocabulary <= hub
    angles = section(doc, "`<prefix>/angles`")
    for word in (*REASONS, *MODES, *CONTENTS):
        assert _mentions(angles, word), word
    health = section(doc, "`<prefix>/health`")
    for state in (*NMT_STATE_NAMES.values(), "missing", "lost", "error"):
        assert f"`{state}`" in health, state


# ------------------------------------------------------------------------------------------
# telemetry.md: the Python subscriber, run against a live publisher

def _example() -> str:
    body = section(_read("telemetry.md"), "A subscriber in Python")
    m = re.search(r"```python\n(.*?)```", body, re.DOTALL)
    assert m, "no python block"
    return m.group(1)


def test_the_python_subscriber_in_telemetry_md_runs_against_a_live_publisher(published):
    import zenoh

    from rsra.daq.runtime.telemetry import TelemetryPublisher, zenoh_config
    from tests.helpers_net import free_tcp_port

    cfg = load_config()
    code = _example()
    default_ep = "tcp/127.0.0.1:7447"
    assert default_ep in code and cfg.telemetry.listen == (default_ep,)
    assert f'"{cfg.telemetry.prefix}/hub_loads"' in code
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    code = code.replace(default_ep, ep)

    hub = [p for k, p in published if k == "hub_loads"]
    angles = next(p for k, p in published if k == "angles")
    session = zenoh.open(zenoh_config(cfg.telemetry, listen=[ep]))
    pub = TelemetryPublisher(session, cfg.telemetry.prefix, cfg.effective())
    stop = threading.Event()
    try:
        pub.publish("angles", angles)  # state/angles has an answer for the late joiner
        proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)

        def feed() -> None:  # the recorded hub loads, seq counting on, until it is done
            i = 0
            while proc.poll() is None and not stop.is_set():
                rec = dict(hub[i % len(hub)], seq=i)
                pub.publish("hub_loads", rec)
                i += 1
                if i % 50 == 0:
                    stop.wait(0.005)  # about 10k messages/s: a fast rig, not a flood

        th = threading.Thread(target=feed, daemon=True)
        th.start()
        try:
            out, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
            stop.set()
            th.join(timeout=10)
    finally:
        pub.close()
        session.close()
    assert proc.returncode == 0, err
    lines = out.splitlines()
    first = lines[0]
    assert first.startswith("angles (rad): ")
    shown = ast.literal_eval(first.split(": ", 1)[1])
    assert shown == dict(zip(angles["names"], angles["alpha"]))
    received, missed, seqs = 0, 0, []
    for line in lines[1:]:
        m = re.match(r"^missed (\d+) samples$", line)
        if m:
            missed += int(m.group(1))
            continue
        m = re.match(r"^(\d+) (\S+) Z = (-?\d+) N (\[.*\])$", line)
        assert m, line
        seq = int(m.group(1))
        src = hub[seq % len(hub)]
        assert float(m.group(2)) == src["t"]
        assert int(m.group(3)) == round(src["H"][2])
        assert ast.literal_eval(m.group(4)) == src["flags"]
        seqs.append(seq)
        received += 1
    # every hub-load record of this run has H (no invalid stretch), so every message printed
    assert all(h["H"] is not None for h in hub)
    assert received == 2000
    assert seqs == sorted(seqs) and received + missed == seqs[-1] - seqs[0] + 1


# ------------------------------------------------------------------------------------------
# links between the pages

def _slug(heading: str) -> str:
    """The anchor a Markdown renderer (GitHub) gives a heading."""
    s = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return s.replace(" ", "-")


@pytest.mark.parametrize("page", sorted(p.name for p in DOCS.glob("*.md")))
def test_relative_links_point_at_existing_pages_and_headings(page):
    text = _read(page)
    text = re.sub(r"```.*?```", "", text, flags=re.DOTALL)  # not inside code
    broken = []
    for target in re.findall(r"\]\(([^)\s]+)\)", text):
        if re.match(r"^[a-z]+:", target):
            continue  # an external address
        file, _, anchor = target.partition("#")
        path = DOCS / file if file else DOCS / page
        if not path.is_file():
            broken.append(target)
            continue
        if anchor:
            headings = re.findall(r"^#+\s+(.*)$", path.read_text(encoding="utf-8"), re.MULTILINE)
            if anchor not in {_slug(h) for h in headings}:
                broken.append(target)
    assert not broken, f"{page}: broken links {broken}"


def test_readme_benchmark_table_is_generated_from_the_committed_results():
    """README's table is what bench.readme renders from bench/results (no hand edits)."""
    from bench.readme import BEGIN, END, README, render_table

    text = README.read_text(encoding="utf-8")
    assert BEGIN in text and END in text
    table = text.split(BEGIN, 1)[1].split(END, 1)[0]
    assert table.strip() == render_table().strip()
    rows = [r for r in table.splitlines() if r.startswith("| ") and not r.startswith("| bench")]
    assert rows and all(len(r.replace("\\|", "").split("|")) == 9 for r in rows)  # 7 cells


# ------------------------------------------------------------------------------------------
# citations in the code resolve to the project's docs (issue 15)

CODE_DIRS = ("daq", "estimator", "sim_bus", "config", "bench", "rsra", "tests")
THIS_FILE = Path(__file__).resolve()  # its examples of broken citations are not citations
# docs/performance.md and docs/architecture.md are written on other branches and merged by
# the lead: citations of them are checked only once the file exists.
PENDING_DOCS = {"performance", "architecture"}
# `<name>.md` in the code that are not pages of docs/: generated files and report outputs
# (summary.md of rsra report, survey.md of rsra survey).
NOT_DOCS = {"README", "RESULTS", "summary", "survey"}
# a § that is not a citation of our docs: the CANopen standard, and benchmark A2's labels
# "σ_§4" and "≤ 0.8 × the §4 bound" (output: they are in the README's generated table)
BARE_SECTION_OK = re.compile(r"CiA 301 §|σ_§|× the §")
_DOC = r"(?<![\w.-])(?:docs/)?(?P<doc>[A-Za-z][\w-]*)(?P<md>\.md)?(?:'s)?[,:]?\s+(?=§)"
_ITEM = re.compile(r'§\s?(?P<n>\d+(?:\.\d+)?)(?:(?P<how>,?\s|:\s)"(?P<q>[^"]+)")?')
_NEXT = re.compile(r"\s*(?:,|–|-|and|to)\s*(?=§)")


def _code_texts():
    """(path, text) of every .py under the code folders, comment and docstring lines joined
    (a citation may wrap)."""
    for d in CODE_DIRS:
        for path in sorted((ROOT / d).rglob("*.py")):
            if path.resolve() == THIS_FILE:
                continue
            raw = path.read_text(encoding="utf-8")
            yield path.relative_to(ROOT), re.sub(r"\n\s*(?:#\s*)?", " ", raw)


def _numbered_sections(doc: str) -> dict[str, tuple[str, str]]:
    """number -> (title, body) of every `## N. title` / `### N.M title` heading of docs/<doc>.md."""
    lines = _read(f"{doc}.md").splitlines()
    out = {}
    for i, line in enumerate(lines):
        m = re.match(r"^(#+)\s+(\d+(?:\.\d+)?)\.?\s+(.*)$", line)
        if not m:
            continue
        level, body = len(m.group(1)), []
        for nxt in lines[i + 1:]:
            m2 = re.match(r"^(#+)\s", nxt)
            if m2 and len(m2.group(1)) <= level:
                break
            body.append(nxt)
        out[m.group(2)] = (m.group(3), "\n".join(body))
    return out


def _norm(s: str) -> str:
    return " ".join(s.replace("`", "").split()).lower()


def citations(text: str):
    """(doc, section number, how, quote, start) of every `<doc>(.md) §N` citation in a text,
    lists and ranges included (`model.md §4, §6, §7`, `§2–§3`, `§1 "Nodes", §2 "SYNC…"`);
    how is "name" for `§N "Title"` and "quote" for `§N: "words of the section"`."""
    names = {p.stem for p in DOCS.glob("*.md")} | PENDING_DOCS
    for m in re.finditer(_DOC, text):
        if not m.group("md") and m.group("doc").lower() not in names:
            continue  # "the §4": not a citation (a bare §, reported as such)
        pos = m.end()
        while True:
            it = _ITEM.match(text, pos)
            if not it:
                break
            how = None if it.group("q") is None else ("quote" if ":" in it.group("how") else "name")
            yield m.group("doc"), it.group("n"), how, it.group("q"), it.start()
            pos = it.end()
            sep = _NEXT.match(text, pos)
            if not sep:
                break
            pos = sep.end()


def citation_problems(texts) -> list[str]:
    docs = {p.stem for p in DOCS.glob("*.md")}
    sections: dict[str, dict] = {}
    problems = []
    for path, text in texts:
        covered = set()
        for doc, n, how, quote, at in citations(text):
            covered.add(at)
            name = doc.lower()
            if name in PENDING_DOCS and name not in docs:
                continue
            if name not in docs:
                problems.append(f"{path}: {doc} §{n}: no docs/{name}.md")
                continue
            secs = sections.setdefault(name, _numbered_sections(name))
            if n not in secs:
                problems.append(f"{path}: {doc} §{n}: docs/{name}.md has no section {n}")
            elif how == "name" and _norm(quote) not in _norm(secs[n][0]):
                problems.append(f'{path}: {doc} §{n} "{quote}": its heading is "{secs[n][0]}"')
            elif how == "quote" and _norm(quote) not in _norm(secs[n][1]):
                problems.append(f'{path}: {doc} §{n}: "{quote}" is not in that section')
        for m in re.finditer("§", text):
            if m.start() not in covered and not BARE_SECTION_OK.search(
                    text[max(0, m.start() - 8):m.end()]):
                problems.append(f"{path}: a § that names no doc: …{text[max(0, m.start() - 30):m.end() + 10]}…")
        for m in re.finditer(r'(?<![\w.-])(?:docs/)?([\w-]+)\.md,? "([^"]+)"', text):
            name, quote = m.group(1), m.group(2)  # a section by its title: `reliability.md "Soak"`
            if name in docs and not any(_norm(quote) in _norm(h) for h in re.findall(
                    r"^#+\s+(.*)$", _read(f"{name}.md"), re.MULTILINE)):
                problems.append(f'{path}: {name}.md "{quote}": no such heading')
        for m in re.finditer(r"(?<![\w.-])((?:[\w.-]+/)*)([\w-]+)\.md\b", text):
            prefix, name = m.group(1), m.group(2)
            if prefix not in ("", "docs/") or name in NOT_DOCS or name in PENDING_DOCS:
                continue
            if name not in docs:
                problems.append(f"{path}: {name}.md is not in docs/")
    return problems


def test_every_citation_in_the_code_resolves_to_a_numbered_section_of_the_docs():
    texts = list(_code_texts())
    assert len(texts) > 100
    n = sum(1 for _, t in texts for _ in citations(t))
    assert n > 150  # the scanner finds the citations at all
    problems = citation_problems(texts)
    assert not problems, "\n".join(problems)


def test_the_citation_check_fails_on_a_section_that_does_not_resolve():
    bad = [("x.py", 'model §9 and model.md §7.9, bus.md §1 "Nodez", model §7: "not written there"'),
           ("y.py", "the §4 noise; see nowhere.md; spec bus.md §2 and docs/cli.md §15"),
           ("z.py", 'docs/reliability.md "Soak"; reliability.md, "No such part"')]
    problems = citation_problems(bad)
    assert len(problems) == 7, problems
    assert all(s in "\n".join(problems) for s in
               ("no section 9", "no section 7.9", "Nodez", "not written there", "names no doc",
                "No such part"))
    assert any("nowhere.md is not in docs/" in p for p in problems)


def test_readme_demo_picture_has_the_columns_and_phases_the_demo_prints(cfg):
    """The README's demo picture is the view the code draws today (issue 28): the hub-load
    table's columns and the summary's phase lines, not an older view's."""
    import io

    from rich.console import Console

    from rsra.daq.cli.demo_view import DemoState, render
    from rsra.estimator.noise_budget import noise_budget

    model = cfg.rig_model()
    state = DemoState(cfg, noise_budget(model, cfg.identification.initial_angles_rad).total,
                      model.geometry.angle_names)
    con = Console(file=io.StringIO(), width=128)
    con.print(render(state, "ground-test", "si"))
    drawn = con.file.getvalue()
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    picture = readme[readme.index("```\n╭"):readme.index("(Above: `rsra demo")]
    header = next(x for x in drawn.splitlines() if "┃ axis" in x)
    cols = [c.strip() for c in header.split("┃")[1:-1] if c.strip()][:7]
    assert cols == ["axis", "truth", "Ĥ", "static", "σ Ĥ", "err/σ", ">3σ"], cols
    for c in cols:
        assert c in picture
    for phase in ("H start", "H steady", "H_static steady", "steady: calibrated steady state"):
        assert phase in picture, phase
