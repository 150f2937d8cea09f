"""``forensics demo``: the whole toolkit on built-in data, written as one HTML report."""
from __future__ import annotations

import argparse

from forensics.cli.common import add_execution_options, command_parser, emit, executor_for, info, progress_for, seed


def register(sub) -> None:
    parser = command_parser(sub, "demo", "run every capability on built-in simulated data and write a report",
                            "forensics demo --out report --seed 0",
                            "Simulate sensors whose truth is known, run every estimator on them, and write "
                            "OUT/index.html with the plots.  Takes under two minutes on 2 cores.")
    parser.add_argument("--out", default="report", help="report folder (default ./report)")
    parser.add_argument("--seed", type=seed, default=0, help="random seed (default 0)")
    parser.add_argument("--only", action="append", metavar="SECTION",
                        help="run only this section (repeatable): ageing, prnu, attribution, defects, check, impact")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of the summary")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--force", action="store_true", default=True,
                        help="replace an existing report folder (default: yes, the demo's own output)")
    add_execution_options(parser)
    parser.set_defaults(handler=run, inputs=(), outputs=("--out",))


def run(args: argparse.Namespace) -> int:
    from forensics._shared.errors import UsageError
    from forensics.demo import available_sections, run_demo

    unknown = sorted(set(args.only or ()) - set(available_sections()))
    if unknown:
        raise UsageError(f"--only {', '.join(unknown)}: no such section; choose from {', '.join(available_sections())}")
    info(args, f"forensics demo: writing {args.out}/ …")
    with executor_for(args) as executor:
        result = run_demo(args.out, rng=args.seed, force=args.force, progress=progress_for(args), only=args.only,
                          executor=executor)

    def summary() -> str:
        lines = []
        for section in result.sections:
            lines.extend(section.summary)
        lines.append(f"report: {result.report_path.resolve()}  ({result.seconds:.0f} s)")
        return "\n".join(lines)

    emit(args, summary, result.to_dict())
    return 0
