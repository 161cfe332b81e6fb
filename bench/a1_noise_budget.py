"""A1 — the noise budget (model.md §4) on the default config against the report's Table I.

Target (performance.md): reproduce Table I's instrumentation-noise column within 1 % on
every axis.

What we compare against. Table I of the report is badly garbled in the OCR
(/work/shared/seed/rsra-load-cell-report.ocr.txt, lines 482–489: "SOOlb Total Load Ct,lIs
Ac(.e1" then one row per axis X Y Z L M N). Its instrumentation-noise part has three
columns — total, load-cell part, accelerometer part — in lb and ft·lb. The readings below
are transcribed token by token with this OCR's habits (":!" is 2, "-I"/"-t" are 4, "I" is 1,
"S"/"s" is 8 or 4 by context). Each entry is graded:

* ``clear`` — the digits read unambiguously;
* ``probable`` — one glyph needs the OCR's habits to read;
* ``conflicting`` — reads clearly but contradicts its own row (kept, reported, not used for
  the decision — the reason is given);
* ``illegible`` — no number can be read (not compared).

The figure is the largest |ours − report| / report over the clear and probable entries;
the line also gives every entry and the figure with the conflicting one included.
"""
from __future__ import annotations

import numpy as np

from bench.common import arg_parser, writer_from_args
from rsra.config.rig import load_config
from rsra.config.units import to_units
from rsra.estimator.noise_budget import AXES, noise_budget

BENCH = "a1_noise_budget"
TOLERANCE = 0.01
COLUMNS = ("total", "load_cells", "accelerometers")

# (axis, column) -> (OCR token, value read or None, grade, note)
TABLE_I: dict[tuple[str, str], tuple[str, float | None, str, str]] = {
    ("X", "total"): ("::09", 309.0, "probable", "row '211 ::09 :!5 308'"),
    ("X", "load_cells"): (":!5", 25.0, "clear", ""),
    ("X", "accelerometers"): ("308", 308.0, "clear", ""),
    ("Y", "total"): ("31:!", 312.0, "conflicting",
                     ("reads 312, but the row's accelerometer part 305 and any load-cell part "
                     "the two lateral cells can give (√2 × 25 lb = 35 lb, the same 0.1 % FS "
                     "cells as X's 25 lb) combine to 307; 312 would need a 66 lb load-cell "
                     "part")),
    ("Y", "load_cells"): (":\\j", None, "illegible", ""),
    ("Y", "accelerometers"): ("305", 305.0, "clear", ""),
    ("Z", "total"): (":~ I :!", 312.0, "probable", "row ':!9 :~ I :! :iO :ms'"),
    ("Z", "load_cells"): (":iO", 50.0, "probable", ""),
    ("Z", "accelerometers"): (":ms", None, "illegible", ""),
    ("L", "total"): ("-I-tG", 446.0, "probable", "row ':.!Iij -I-tG li9 -lOS'"),
    ("L", "load_cells"): ("li9", 179.0, "probable", ""),
    ("L", "accelerometers"): ("-lOS", 408.0, "probable", ""),
    ("M", "total"): (",Ii", None, "illegible",
                     ("row ',Ii 136 H, ·n~': the 800 lb column is missing, so 136 is the "
                     "load-cell part")),
    ("M", "load_cells"): ("136", 136.0, "probable", "position in the row inferred"),
    ("M", "accelerometers"): ("H,", None, "illegible", ""),
    ("N", "total"): ("1sI", 141.0, "probable", "row ':!I-t 1sI 131 51'"),
    ("N", "load_cells"): ("131", 131.0, "clear", ""),
    ("N", "accelerometers"): ("51", 51.0, "clear", ""),
}


def main(argv: list[str] | None = None) -> int:
    args = arg_parser(__doc__.splitlines()[0]).parse_args(argv)
    w = writer_from_args(BENCH, args)
    cfg = load_config()
    nb = noise_budget(cfg.rig_model(), cfg.identification.initial_angles_rad)
    ours = {c: to_units(getattr(nb, c), "us") for c in COLUMNS}
    entries, used, all_read = [], [], []
    for i, ax in enumerate(AXES):
        for c in COLUMNS:
            token, value, grade, note = TABLE_I[(ax, c)]
            mine = float(ours[c][i])
            dev = None if value is None else (mine - value) / value
            entries.append({"axis": ax, "column": c, "ocr": token, "report": value,
                            "grade": grade, "ours": round(mine, 2),
                            "deviation": None if dev is None else round(dev, 5), "note": note})
            if dev is not None:
                all_read.append(abs(dev))
                if grade in ("clear", "probable"):
                    used.append(abs(dev))
    worst = float(np.max(used))
    worst_all = float(np.max(all_read))
    w.add("table_I_instrumentation_noise", worst * 100.0, "% (largest |deviation|)",
          peer="report Table I (OCR, clear and probable entries)", peer_figure=None,
          target="within 1 % of Table I on every axis", met=worst <= TOLERANCE,
          entries_compared=len(used), entries_read=len(all_read),
          entries_total=len(entries), largest_deviation_including_conflicting_pct=worst_all * 100,
          met_including_conflicting=worst_all <= TOLERANCE, units="lb, ft·lb",
          ours_si={c: getattr(nb, c) for c in COLUMNS}, entries=entries,
          source="/work/shared/seed/rsra-load-cell-report.ocr.txt lines 482-489")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
