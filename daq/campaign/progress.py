"""What `rsra campaign run` shows: on a terminal a live bar (recordings done, samples/s over
all workers, ETA, failures), off a terminal one plain line per finished recording; a
summary table at the end (rich)."""
from __future__ import annotations

import sys
import time
from typing import Any, TextIO


class Progress:
    def __init__(self, out: TextIO | None = None, live: bool | None = None):
        self.out = out or sys.stdout
        self.console = console(self.out)
        #: a live bar (a terminal), or plain lines
        self.live = self.console.is_terminal if live is None else live
        self.total = 0
        self.bytes_total = 0
        self.bytes_done = 0
        self.finished = 0
        self.failed = 0
        self.samples = 0
        self.t0 = time.monotonic()
        self._bar: Any = None
        self._task: Any = None

    def start(self, total: int, size: int, describe: str) -> None:
        self.total, self.bytes_total, self.t0 = total, max(size, 1), time.monotonic()
        self.console.print(f"campaign: {total} recordings to run on {describe}")
        if self.live:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn

            self._bar = Progress(TextColumn("{task.description}"), BarColumn(),
                                 MofNCompleteColumn(), TextColumn("{task.fields[info]}"),
                                 console=self.console, transient=True)
            self._task = self._bar.add_task("recordings", total=total, info="")
            self._bar.start()

    def rate(self) -> float:
        return self.samples / max(time.monotonic() - self.t0, 1e-9)

    def eta(self) -> float | None:
        if not self.bytes_done:
            return None
        el = time.monotonic() - self.t0
        return el * (self.bytes_total - self.bytes_done) / self.bytes_done

    def done(self, item: Any, row: dict[str, Any]) -> None:
        self.finished += 1
        self.bytes_done += item.size
        self.samples += row.get("samples") or 0
        if row.get("status") != "ok":
            self.failed += 1
        eta = self.eta()
        info = (f"{self.rate():,.0f} samples/s  ETA {'-' if eta is None else f'{eta:.0f} s'}"
                f"  failed {self.failed}")
        if self._bar is not None:
            self._bar.update(self._task, advance=1, info=info)
            if row.get("status") != "ok":
                self._bar.console.print(f"failed: {item.recording}: {row.get('reason')}")
        else:
            what = (f"ok, {row.get('samples')} samples in {row.get('wall_s') or 0:.1f} s"
                    if row.get("status") == "ok" else f"FAILED: {row.get('reason')}")
            self.console.print(f"[{self.finished}/{self.total or '-'}] {item.recording}: "
                               f"{what}  ({info})", markup=False)

    def interrupted(self, pending: int) -> None:
        self.stop()
        self.console.print(f"campaign: interrupted: {pending} recordings not run (cancelled); "
                           "the finished ones are kept, the manifest says which")

    def stop(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None

    def summary(self, plan: Any, rows: dict[str, dict[str, Any]]) -> None:
        self.stop()
        t = table(f"campaign {plan.dataset}", ("recording", "action", "status", "samples",
                                                "lost", "accepted runs", "wall s",
                                                "why / reason"))
        for item in plan.items:
            r = rows.get(item.recording, {})
            ran = item.action != "skip"
            t.add_row(item.recording, item.action, str(r.get("status") or "-"),
                      _n(r.get("samples")), _n(r.get("lost_samples")),
                      _n(r.get("accepted_runs")),
                      f"{r['wall_s']:.1f}" if ran and r.get("wall_s") else "-",
                      (r.get("reason") or item.why) if r.get("status") == "failed"
                      else item.why)
        self.console.print(t)
        el = time.monotonic() - self.t0
        counts = {a: len(plan.of(a)) for a in ("run", "skip", "fail")}
        failed = sum(1 for i in plan.items if rows.get(i.recording, {}).get("status")
                     == "failed" and i.action != "skip")
        self.console.print(f"campaign: {counts['run']} run, {counts['skip']} skipped, "
                           f"{failed} failed; {self.samples} samples in {el:.1f} s "
                           f"({self.rate():,.0f} samples/s)", markup=False)


NUMERIC = ("samples", "lost", "accepted runs", "wall s")
PLAIN_WIDTH = 200  # columns of a table off a terminal (a log file: the ids stay whole)


def console(out: TextIO | None = None):
    """A rich console on ``out`` (standard output): the terminal's width, or wide off one."""
    from rich.console import Console

    out = out or sys.stdout
    c = Console(file=out, highlight=False, soft_wrap=True)
    if not c.is_terminal:
        c = Console(file=out, highlight=False, soft_wrap=True, width=PLAIN_WIDTH)
    return c


def table(title: str, columns: tuple[str, ...]):
    """A rich table of recordings: every cell folded, never cut (an id stays whole)."""
    from rich.table import Table

    t = Table(title=title, title_justify="left")
    for c in columns:
        t.add_column(c, overflow="fold", no_wrap=c == "recording",
                     justify="right" if c in NUMERIC else "left")
    return t


def _n(v: Any) -> str:
    return "-" if v is None else str(v)
