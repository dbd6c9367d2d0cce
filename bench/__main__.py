"""The benchmark runner: ``python -m bench SUITE [--case NAME,...] [--config FILE.json] [--quick]``.

Suites group the measurements by the question they answer; each is a set of named cases
(``python -m bench SUITE --list``):

- ``accuracy``: classical matching on real pairs, against pyFM (``bench/accuracy.py``);
- ``speed``: operators, bases, heat kernels, eigensolvers (``bench/speed.py``), the whole
  matching pipeline, nearest neighbours, collections, threads (``bench/speed_match.py``), the
  differentiable solver and a training step (``bench/speed_torch.py``);
- ``learned``: trained checkpoints, convergence, test-time adaptation, the second stage
  (``bench/learned.py``);
- ``robustness``: every reader fed mutated files (``bench/fuzz.py``; a bounded run is
  ``tests/test_fuzz.py``).

A case's settings are the defaults of ``bench/configs/<suite>.json`` (its entry ``<case>``),
then its ``quick`` entry with ``--quick`` (the demo pair, tiny synthetic meshes: a smoke run),
then ``--config FILE.json`` (``{"<case>": {...}}``, or flat settings for the cases run), then
``--set key=value`` (a JSON value, else a string). Each case writes
``bench/results/<suite>_<case>[_<name>].md`` (the table, its settings, versions, load), and where
it has them the rows as ``.csv`` and a ``.png``; ``--out`` writes elsewhere. Times are wall-clock
ratios against a baseline run in the same process. A case whose data or optional library is
absent is skipped with one line; real data is read from ``../shared/data`` (``--data``).
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import time
from pathlib import Path

from . import common
from .common import CONFIG_DIR, RESULTS_DIR, Report, Settings, Skip, code_state, json_line, load_note, log

#: suite -> modules holding its cases (``CASES``: name -> function(settings, report)).
SUITES = {
    "accuracy": ("bench.accuracy",),
    "speed": ("bench.speed", "bench.speed_match", "bench.speed_dense", "bench.speed_torch"),
    "learned": ("bench.learned",),
    "robustness": ("bench.fuzz",),
}


def question(fn) -> str:
    """The first paragraph of a case's docstring: the question it answers."""
    return " ".join((fn.__doc__ or "").split("\n\n")[0].split())


def cases(suite: str) -> dict:
    """``name -> case function`` of a suite, in the order of its modules."""
    out = {}
    for module in SUITES[suite]:
        out |= importlib.import_module(module).CASES
    return out


def parse_value(text: str):
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def settings(suite: str, case: str, quick: bool, config: dict, overrides: dict) -> Settings:
    """The merged settings of one case (see the module docstring)."""
    defaults = json.loads((CONFIG_DIR / f"{suite}.json").read_text())
    if case not in defaults:
        raise SystemExit(f"bench/configs/{suite}.json has no entry for the case {case!r}")
    merged = {k: v for k, v in defaults[case].items() if k != "quick"}
    known = set(merged)
    if quick:
        merged |= defaults[case].get("quick", {})
    names = set(cases(suite))
    given = {k: v for k, v in config.items() if k not in names}  # flat settings
    merged |= {k: v for k, v in given.items() if k in known} | config.get(case, {}) | overrides
    unknown = (set(config.get(case, {})) | set(overrides)) - known
    if unknown:
        raise SystemExit(
            f"{suite} {case}: unknown setting(s) {', '.join(sorted(unknown))}; its settings are "
            f"{', '.join(sorted(known))} (bench/configs/{suite}.json)"
        )
    return Settings(merged)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m bench",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=__doc__.split("\n\n", 1)[1],
    )
    p.add_argument("suite", choices=list(SUITES))
    p.add_argument("--case", default="", help="comma list of cases (default: every case of the suite)")
    p.add_argument("--list", action="store_true", help="list the suite's cases and their questions")
    p.add_argument("--config", type=Path, help="a JSON file of settings (see above)")
    p.add_argument("--quick", action="store_true", help="the smoke settings: demo pair, tiny meshes")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="one setting (repeatable)")
    p.add_argument("--name", default="", help="results in <suite>_<case>_<name>.md (a named variant)")
    p.add_argument(
        "--out", type=Path, default=RESULTS_DIR, help="folder of the results (default bench/results)"
    )
    p.add_argument("--data", type=Path, help="folder of the real data (default ../shared/data)")
    return p


def main(argv: list[str] | None = None) -> list[Path]:
    """Run the cases; returns the written ``.md`` files (skipped cases write none)."""
    args = build_parser().parse_args(argv)
    every = cases(args.suite)
    if args.list:
        for name, fn in every.items():
            print(f"{name:18s} {question(fn)}")
        return []
    chosen = [c.strip() for c in args.case.split(",") if c.strip()] or list(every)
    bad = [c for c in chosen if c not in every]
    if bad:
        raise SystemExit(f"unknown case(s) {', '.join(bad)} of {args.suite}: one of {', '.join(every)}")
    if args.data is not None:
        common.DATA_DIR = args.data.resolve()
    config = json.loads(args.config.read_text()) if args.config else {}
    overrides = {}
    for item in args.set:
        key, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"--set {item!r}: expected KEY=VALUE")
        overrides[key.strip()] = parse_value(value)
    written = []
    for case in chosen:
        cfg = settings(args.suite, case, args.quick, config, overrides)
        stem = f"{args.suite}_{case}" + (f"_{args.name}" if args.name else "")
        command = "python -m bench " + " ".join(sys.argv[1:] if argv is None else argv)
        header = (
            f"# {args.suite} / {case}: {question(every[case])}\n\n"
            f"`{command}`{' (quick: a smoke run, not figures)' if args.quick else ''}; settings "
            f"`{json_line(dict(cfg))}`; {common.versions('scipy', 'torch')}; {code_state()}; "
            f"{load_note()} at start."
        )
        report = Report(stem, args.out, header)
        t0 = time.perf_counter()
        try:
            every[case](cfg, report)
        except Skip as why:
            log(f"{args.suite} {case}: skipped: {why}")
            continue
        except KeyboardInterrupt:
            report.add("**Interrupted**: the tables above hold what finished.")
        pairs = sys.modules.get("bench.pairs")
        if pairs is not None and pairs.ERRORS:
            report.add(pairs.errors_section())
            pairs.ERRORS.clear()
        report.add(f"{load_note()} at end; {time.perf_counter() - t0:.0f} s in all.")
        written.append(report.save())
    return written


if __name__ == "__main__":
    main()
