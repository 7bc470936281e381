"""Command line: `intercap validate | run | eval | synth`."""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path


def _cmd_validate(args) -> int:
    from intercap.session import format_report, validate

    session, problems = validate(args.session)
    print(format_report(session, problems))
    return 1 if any(p.fatal for p in problems) else 0


def _cmd_run(args) -> int:
    from intercap.config import load_config
    from intercap.pipeline import run_pipeline

    overrides = list(args.set or [])
    if args.stages:
        overrides.append(f"run.stages={args.stages}")
    if args.force:
        overrides.append("run.force=true")
    if args.device:
        overrides.append(f"run.device={args.device}")
    cfg = load_config(args.config, overrides)
    metrics = run_pipeline(args.session, args.out, cfg, progress=not args.quiet)
    for stage, figures in metrics.items():
        shown = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in figures.items())
        print(f"{stage}: {shown}")
    print(f"results in {Path(args.out).resolve()}")
    return 0


def _cmd_eval(args) -> int:
    from intercap.evaluation.evaluate import evaluate
    from intercap.evaluation.table import format_table, write_json

    result = evaluate(args.out, args.gt)
    print(format_table(result))
    json_path = Path(args.json) if args.json else Path(args.out) / "eval.json"
    write_json(result, json_path)
    print(f"written {json_path}")
    return 0


def _cmd_synth(args) -> int:
    from intercap.synth.generator import config_from_args, generate_session

    path = generate_session(config_from_args(args), args.out)
    print(f"synthetic session written to {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="intercap", description="Multi-view RGB-D human-object capture.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("validate", help="check a session folder and summarise it")
    p.add_argument("session")
    p.set_defaults(func=_cmd_validate)

    p = sub.add_parser("run", help="run the pipeline stages on a session (resumable)")
    p.add_argument("session")
    p.add_argument("--out", required=True, help="results folder")
    p.add_argument("--config", help="YAML file overriding the defaults")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override one setting (repeatable)")
    p.add_argument("--stages", help="comma-separated stages to run (default: all built stages)")
    p.add_argument("--force", action="store_true", help="redo stages whose output is already saved")
    p.add_argument("--device", help="cpu or cuda")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("eval", help="compare a results folder with a session's ground truth")
    p.add_argument("out", help="results folder written by `intercap run`")
    p.add_argument("--gt", required=True, help="session folder with ground_truth/")
    p.add_argument("--json", help="where to write the figures (default OUT/eval.json)")
    p.set_defaults(func=_cmd_eval)

    p = sub.add_parser("synth", help="write a synthetic session with ground truth")
    from intercap.synth.generator import build_arg_parser

    build_arg_parser(p)  # adds OUT and the generator's options
    p.set_defaults(func=_cmd_synth)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    from intercap.config import ConfigError
    from intercap.pipeline import StageError
    from intercap.session import SessionError

    try:
        return args.func(args)
    except SessionError as exc:  # lists every problem found
        print(f"intercap {args.command}: {exc}", file=sys.stderr)
        return 2
    except (ConfigError, StageError, FileNotFoundError, ValueError) as exc:
        print(f"intercap {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
