"""`rsra config show|list`: the effective rig — the packaged default with the ``--config`` layers
applied in order — as TOML, each value with the file it came from (docs/cli.md,
docs/configuration.md "Layers")."""
from __future__ import annotations

import argparse
import json
from typing import Any


def add_parser(sub, name: str) -> argparse.ArgumentParser:
    from rsra.daq.cli.options import common_options

    p = sub.add_parser(name, help="the effective rig config, each value with its file",
                       description="show: the rig the other commands would use with the same "
                       "--config files (the packaged default rig, then each --config in order, "
                       "each after the rig it extends), printed as TOML with the file every "
                       "value came from as a comment; checked as every command checks it.")
    p.add_argument("action", choices=("show", "list"), metavar="show|list",
                   help="show: the effective rig; list: the packaged rigs by name (what "
                   "--config NAME and extends = \"NAME\" accept)")
    common_options(p, units=False)
    p.add_argument("--json", action="store_true",
                   help='print {"rig": the effective rig, "origins": {dotted key: file}}')
    return p


def _value(v: Any) -> str:
    """A TOML value (strings, numbers, booleans, arrays of them: JSON spells them alike)."""
    if isinstance(v, float) and v == int(v) and abs(v) < 1e15:
        return repr(v)
    return json.dumps(v, ensure_ascii=False)


def toml_lines(raw: dict, origins: dict[str, str]) -> list[str]:
    """The effective rig as TOML, each value with ``# <file>``."""
    from rsra.config.rig import origin_of

    lines: list[str] = []

    def table(d: dict, path: str, header: str | None) -> None:
        scalars = [(k, v) for k, v in d.items() if not isinstance(v, dict)
                   and not (isinstance(v, list) and v and all(isinstance(x, dict) for x in v))]
        if header is not None and (scalars or not d):
            lines.append("")
            lines.append(header)
        width = max((len(f"{k} = {_value(v)}") for k, v in scalars), default=0) + 2
        for k, v in scalars:
            key = f"{path}.{k}" if path else k
            text = f"{k} = {_value(v)}"
            lines.append(f"{text.ljust(width)}# {origin_of(key, origins) or '?'}")
        for k, v in d.items():
            key = f"{path}.{k}" if path else k
            if isinstance(v, dict):
                table(v, key, f"[{key}]")
            elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):
                for i, item in enumerate(v):
                    lines.append("")
                    lines.append(f"[[{key}]]  # {origin_of(key, origins) or '?'}")
                    for a, b in item.items():
                        lines.append(f"{a} = {_value(b)}")

    table(raw, "", None)
    return lines


def list_rigs(as_json: bool) -> int:
    """`rsra config list`: the packaged rigs, each with its file and first comment line."""
    from rsra.config.rig import load_config, packaged_rigs

    rows = []
    for name, path in packaged_rigs().items():
        cfg = load_config(None if name == "default" else path)
        first = next((ln.lstrip("# ").strip() for ln in path.read_text().splitlines()
                      if ln.startswith("#")), "")
        rows.append({"name": name, "file": str(path), "rig": cfg.rig_name,
                     "prefix": cfg.telemetry.prefix, "about": first})
    if as_json:
        print(json.dumps(rows, ensure_ascii=False, indent=1))
        return 0
    print("packaged rigs (--config NAME, extends = \"NAME\"; a path always wins):")
    for r in rows:
        print(f"  {r['name']:10s} rig.name {r['rig']!r}, telemetry {r['prefix']}: {r['about']}")
        print(f"  {'':10s} {r['file']}")
    return 0


def run(args: argparse.Namespace) -> int:
    from rsra.config.rig import absolute_eds, config_dir, merge_layers
    from rsra.daq.rigmodel import load_rig

    if args.action == "list":
        return list_rigs(args.json)
    load_rig(args.config)  # refused in one line, as by every other command
    raw, origins = merge_layers(args.config)
    # the packaged rig's EDS paths absolute: what is printed is a rig TOML usable anywhere
    raw = absolute_eds(raw, config_dir())
    if args.json:
        print(json.dumps({"rig": raw, "origins": origins}, ensure_ascii=False, indent=1))
        return 0
    files = ", ".join(args.config or ()) or "none"
    print(f"# the effective rig: the packaged default rig, then --config {files}")
    print("# each value: the file it came from (default: the packaged rig)")
    print("\n".join(toml_lines(raw, origins)))
    return 0
