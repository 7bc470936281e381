"""Command line: `intercap validate | run | run-many | eval | synth`."""
from __future__ import annotations

import argparse
import logging
import os
import sys
from contextlib import contextmanager
from pathlib import Path


def _cmd_validate(args) -> int:
    from intercap.session import format_report, validate

    session, problems = validate(args.session)
    print(format_report(session, problems))
    return 1 if any(p.fatal for p in problems) else 0


def _stages_override(stages: str | None) -> list[str]:
    """`--stages a,b` as the override run.stages=a,b; an empty name (`--stages ,`, `a,,b`) is an error
    rather than a silent run of every stage."""
    from intercap.config import ConfigError

    if stages is None:
        return []
    names = [name.strip() for name in stages.split(",")]
    if not all(names):
        raise ConfigError(f"--stages {stages!r}: an empty stage name; give names separated by commas, "
                          "e.g. --stages prepare,detect")
    return [f"run.stages={','.join(names)}"]


def parse_frames(text: str | None) -> tuple[int | None, int | None] | None:
    """`--frames A:B` as (A, B), inclusive; an open end is None."""
    from intercap.config import ConfigError

    if text is None:
        return None
    first, sep, last = text.partition(":")
    try:
        if not sep:
            raise ValueError
        bounds = tuple(int(v) if v.strip() else None for v in (first, last))
    except ValueError:
        raise ConfigError(f"--frames {text!r}: give A:B (inclusive frame indices, e.g. 10:59, 10: or :59)") from None
    if any(v is not None and v < 0 for v in bounds) or (None not in bounds and bounds[0] > bounds[1]):
        raise ConfigError(f"--frames {text!r}: frame indices are >= 0 and A <= B")
    return bounds


def _cmd_run(args) -> int:
    from intercap.config import load_config
    from intercap.pipeline import run_pipeline

    overrides = list(args.set or []) + _stages_override(args.stages)
    if args.force:
        overrides.append("run.force=true")
    if args.device:
        overrides.append(f"run.device={args.device}")
    cfg = load_config(args.config, overrides)
    metrics = run_pipeline(args.session, args.out, cfg, progress=show_progress(args), frames=parse_frames(args.frames))
    for stage, figures in ({} if args.log_quiet else metrics).items():
        shown = ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in figures.items()
                          if not (isinstance(v, list) and v and isinstance(v[0], dict)))  # tables: metrics.json
        print(f"{stage}: {shown}")
    print(f"results in {Path(args.out).resolve()}")
    return 0


def _cmd_eval(args) -> int:
    from intercap.evaluation.evaluate import evaluate
    from intercap.evaluation.table import format_table, write_json

    with holding(args.out):  # not while a run writes the results it reads
        result = evaluate(args.out, args.gt)
        print(format_table(result))
        json_path = Path(args.json) if args.json else Path(args.out) / "eval.json"
        write_json(result, json_path)
    print(f"written {json_path}")
    return 0


@contextmanager
def holding(out_dir):
    """The results folder's lock (`pipeline.results_lock`) while a command reads and writes in it, when
    it is a folder (a missing one is the command's own error to report)."""
    from intercap.pipeline import results_lock

    if not Path(out_dir).is_dir():
        yield
        return
    with results_lock(Path(out_dir)):
        yield


def _cmd_run_many(args) -> int:
    from intercap.batch import format_summary, run_many
    from intercap.config import load_config

    overrides = list(args.set or []) + _stages_override(args.stages)
    cfg = load_config(args.config, overrides + (["run.force=true"] if args.force else []))
    try:
        rows = run_many(args.sessions, args.out, cfg, address=args.address, local=args.local,
                        cpus_per_task=args.cpus_per_task, gpus_per_task=args.gpus_per_task)
    except ImportError as exc:
        print(f"intercap run-many: {exc}", file=sys.stderr)
        return 2
    print(format_summary(rows))
    failed = sum(r.status == "failed" for r in rows)
    summary = Path(args.out).resolve() / "summary.csv"
    print(f"{len(rows) - failed} of {len(rows)} sessions done, {failed} failed; summary in {summary}")
    return 1 if failed else 0


def _cmd_view(args) -> int:
    from intercap.evaluation.viewer import ViewerError, serve

    try:
        serve(args.out, port=args.port, host=args.host, session=args.session, block=True)
    except ViewerError as exc:
        print(f"intercap view: error: {exc}", file=sys.stderr)
        return 2
    return 0


def _cmd_report(args) -> int:
    from intercap.evaluation.report import write_report

    with holding(args.out):
        path = write_report(args.out, session=args.session, gt=args.gt, progress=show_progress(args))
    print(f"report written to {path.resolve()}")
    return 0


def _cmd_synth(args) -> int:
    from intercap.synth.generator import config_from_args, generate_session

    if args.log_quiet or not sys.stderr.isatty():  # `intercap -q synth`, or a log file: no progress bars
        args.quiet = True
    path = generate_session(config_from_args(args), args.out)
    print(f"synthetic session written to {path}")
    return 0


def _cmd_import_k4a(args) -> int:
    from intercap.io.k4a import import_k4a

    r = import_k4a(
        args.out_session, args.recordings, start=args.start, end=args.end, stride=args.stride,
        color_resolution=args.color_resolution, calibration=args.calibration,
        uncalibrated=args.uncalibrated, workers=args.workers, overwrite=args.overwrite,
        object_mesh=args.object, mass_kg=args.mass_kg,
    )
    for line in r["pose_sources"]:
        print(line)
    for cam in r["cameras"]:
        print(f"{cam}: {len(r['dropped'][cam])} dropped frames, {len(r['frames_without_depth'][cam])} without depth")
    if r["placeholder_poses"]:
        print(f"poses of {', '.join(r['placeholder_poses'])} are placeholders (identity): run `intercap calibrate`")
    print(f"{r['frames']} frames at {r['fps']:g} fps imported in {r['seconds']:.2f} s to {Path(args.out_session).resolve()}")
    return 0


def _cmd_import_behave(args) -> int:
    from intercap.io.behave import import_behave

    r = import_behave(args.seq_dir, args.out_session, calib_dir=args.calib, objects_dir=args.objects,
                      overwrite=args.overwrite, start=args.start, end=args.end)
    gaps = f", {len(r['gaps'])} without a folder" if r["gaps"] else ""
    print(f"{r['frames']} frames{gaps} ({', '.join(r['cameras'])}; object {r['object']}, {r['object_fits']} fits) "
          f"at {r['fps']:g} fps imported in {r['seconds']:.2f} s to {Path(args.out_session).resolve()}")
    return 0


def _cmd_import_intercap(args) -> int:
    from intercap.io.intercap_dataset import import_intercap

    r = import_intercap(args.seq_dir, args.out_session, args.calib, objects_dir=args.objects, fits=args.fits,
                        which=args.calibration_set, subject=args.subject, motion=args.motion, fps=args.fps,
                        overwrite=args.overwrite, start=args.start, end=args.end)
    for cam, miss in r["dropped"].items():
        if miss:
            print(f"{cam}: {len(miss)} dropped frames")
    print(f"{r['frames']} frames ({r['calibration']}) imported in {r['seconds']:.2f} s to {Path(args.out_session).resolve()}")
    return 0


def add_import_parsers(sub) -> argparse._SubParsersAction:
    """`intercap import <importer> ...`: the group of importers; returns its subparsers
    so each importer adds itself with `isub.add_parser(name)` + `set_defaults(func=...)`."""
    common = [logging_options()]
    imp = sub.add_parser("import", parents=common, help="import recordings or datasets into a session folder")
    isub = imp.add_subparsers(dest="importer", required=True)

    p = isub.add_parser("k4a", parents=common, help="Azure Kinect recordings (.mkv), no SDK needed")
    p.add_argument("out_session", help="session folder to write (must not exist)")
    p.add_argument("recordings", nargs="+", help="one .mkv per device of a synchronised rig")
    p.add_argument("--start", help="first frame (index, or seconds as 2.5s) of the aligned frames")
    p.add_argument("--end", help="last frame, inclusive (index, or seconds as 10s)")
    p.add_argument("--stride", type=int, default=1, help="keep every n-th frame")
    p.add_argument("--color-resolution", help="downscale colour (and registered depth): WxH or a height, e.g. 360")
    p.add_argument("--calibration", help="calibration.json of ours giving the rig's poses (from `intercap calibrate`); "
                   "devices are matched by serial number where it has them, else by order")
    p.add_argument("--uncalibrated", action="store_true",
                   help="several devices without --calibration: write identity placeholder poses")
    p.add_argument("--object", metavar="MESH", help="the handled object's mesh (.ply or .obj, metres), copied into "
                   "the session; without it the session is body-only")
    p.add_argument("--mass-kg", type=float, help="the object's mass (physics), with --object")
    p.add_argument("--workers", type=int, help="rig: processes, one per device at a time (default: one per device, "
                   "at most the CPU count); one recording: threads (default 2)")
    p.add_argument("--overwrite", action="store_true", help="replace OUT_SESSION if it exists")
    p.set_defaults(func=_cmd_import_k4a)

    p = isub.add_parser("behave", parents=common, help="a BEHAVE sequence (t0000.000/k0.color.jpg ...)")
    p.add_argument("seq_dir", help="BEHAVE sequence folder (sequences/<Date>_<Sub>_<object>...)")
    p.add_argument("out_session", help="session folder to write (must not exist)")
    p.add_argument("--calib", help="BEHAVE's calibs/ folder (<Date>/config/<k>/config.json, intrinsics/<k>/calibration.json)")
    p.add_argument("--objects", help="BEHAVE's objects/ folder (<object>/<object>_f1000.ply)")
    p.add_argument("--start", type=int, help="first frame (index in time order)")
    p.add_argument("--end", type=int, help="last frame, inclusive")
    p.add_argument("--overwrite", action="store_true", help="replace OUT_SESSION if it exists")
    p.set_defaults(func=_cmd_import_behave)

    p = isub.add_parser("intercap", parents=common, help="an InterCap segment (Frames_Cam<k>/color ...)")
    p.add_argument("seq_dir", help="InterCap segment folder (RGBD_Images/<subject>/<motion>/Seg_<n>)")
    p.add_argument("out_session", help="session folder to write (must not exist)")
    p.add_argument("--calib", required=True, help="InterCap's Data/ folder (calibration_first|second|third/Color*.json)")
    p.add_argument("--objects", help="InterCap's objs/ folder (<motion>.ply)")
    p.add_argument("--fits", help="their res_tuned.pkl: object fits as ground_truth/object_poses.npz")
    p.add_argument("--calibration-set", choices=["first", "second", "third"],
                   help="override the calibration session chosen from subject and motion")
    p.add_argument("--subject", type=int, help="subject number (default: from the path)")
    p.add_argument("--motion", type=int, help="motion (object) number (default: from the path)")
    p.add_argument("--fps", type=float, default=30.0)
    p.add_argument("--start", type=int, help="first InterCap frame number")
    p.add_argument("--end", type=int, help="last InterCap frame number, inclusive")
    p.add_argument("--overwrite", action="store_true", help="replace OUT_SESSION if it exists")
    p.set_defaults(func=_cmd_import_intercap)
    return isub


def _cmd_board(args) -> int:
    from intercap.calib.board import board_command

    return board_command(args)


def _cmd_calibrate(args) -> int:
    from intercap.calib.board import calibrate_command

    return calibrate_command(args)


def logging_options(quiet: bool = True) -> argparse.ArgumentParser:
    """-v / -q as a parent of every subcommand, so they are taken after it too (`run S --out O -v`).
    Their defaults are left unset here: a subcommand's default would overwrite the flag given before it."""
    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("-v", "--verbose", dest="log_verbose", action="store_true", default=argparse.SUPPRESS,
                   help="debug logging")
    if quiet:
        p.add_argument("-q", "--quiet", dest="log_quiet", action="store_true", default=argparse.SUPPRESS,
                       help="warnings and errors only, no progress bars")
    return p


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The command line; the options of `synth`, `calibrate` and `board` are added only when that command is
    about to run (`intercap --help` lists the commands without them). They come from light modules
    (`intercap.synth.options`, `intercap.calib.options`): the generator imports torch and trimesh,
    calibration cv2 and open3d, which only the command itself needs."""
    from intercap import __version__

    parser = argparse.ArgumentParser(prog="intercap", description="Multi-view RGB-D human-object capture.")
    parser.add_argument("--version", action="version", version=f"intercap {__version__}")
    parser.add_argument("-v", "--verbose", dest="log_verbose", action="store_true", help="debug logging")
    parser.add_argument("-q", "--quiet", dest="log_quiet", action="store_true",
                        help="warnings and errors only, no progress bars")
    common = [logging_options()]
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("validate", parents=common, help="check a session folder and summarise it")
    p.add_argument("session")
    p.set_defaults(func=_cmd_validate)

    p = sub.add_parser("run", parents=common, help="run the pipeline stages on a session (resumable)")
    p.add_argument("session")
    p.add_argument("--out", required=True, help="results folder")
    p.add_argument("--config", help="YAML file overriding the defaults")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override one setting (repeatable)")
    p.add_argument("--stages", help="comma-separated stages to run (default: all built stages)")
    p.add_argument("--force", action="store_true", help="redo stages whose output is already saved")
    p.add_argument("--device", help="cpu or cuda")
    p.add_argument("--frames", metavar="A:B", help="run on frames A..B only (inclusive, session frame indices; "
                   "A: or :B leave that end open); eval cuts the ground truth to them")
    p.set_defaults(func=_cmd_run)

    p = sub.add_parser("eval", parents=common, help="compare a results folder with a session's ground truth")
    p.add_argument("out", help="results folder written by `intercap run`")
    p.add_argument("--gt", help="session folder with ground_truth/ (without: physics plausibility figures only)")
    p.add_argument("--json", help="where to write the figures (default OUT/eval.json)")
    p.set_defaults(func=_cmd_eval)

    p = sub.add_parser("run-many", parents=common, help="run the pipeline on many sessions as Ray tasks (resumable per session)")
    p.add_argument("sessions", nargs="+", metavar="SESSION_GLOB", help="session folders or glob patterns")
    p.add_argument("--out", required=True, help="ROOT: results go to ROOT/<session name>/, the table to ROOT/summary.csv")
    p.add_argument("--address", help="existing Ray cluster: ray://HEAD:10001, or auto on a cluster node (default: local Ray)")
    p.add_argument("--local", action="store_true", help="no Ray: run the sessions one after another in this process")
    p.add_argument("--config", help="YAML file overriding the defaults")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override one setting (repeatable)")
    p.add_argument("--stages", help="comma-separated stages to run (default: all built stages)")
    p.add_argument("--force", action="store_true", help="redo sessions and stages already done")
    p.add_argument("--cpus-per-task", type=float, default=1, help="Ray CPUs reserved per session (default 1)")
    p.add_argument("--gpus-per-task", type=float, help="Ray GPUs per session (default: 1 with run.device=cuda, else 0)")
    p.set_defaults(func=_cmd_run_many)

    add_import_parsers(sub)

    p = sub.add_parser("view", parents=common, help="interactive 3D viewer of a results folder in the browser (viser)")
    p.add_argument("out", help="results folder written by `intercap run`")
    p.add_argument("--port", type=int, default=0, help="port (default: a free one)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1, this machine only; 0.0.0.0: every interface)")
    p.add_argument("--session", help="the session folder (default: the one recorded in OUT/run.json)")
    p.set_defaults(func=_cmd_view)

    p = sub.add_parser("report", parents=common, help="write OUT/report/index.html: overlays, curves, contact, evaluation")
    p.add_argument("out", help="results folder written by `intercap run`")
    p.add_argument("--gt", help="session folder with ground_truth/: adds the evaluation table and error curves")
    p.add_argument("--session", help="the session folder (default: the one recorded in OUT/run.json)")
    p.set_defaults(func=_cmd_report)

    p = sub.add_parser("synth", parents=[logging_options(quiet=False)], help="write a synthetic session with ground truth")
    if command == "synth":
        from intercap.synth.options import build_arg_parser

        build_arg_parser(p)  # adds OUT and the generator's options
    p.set_defaults(func=_cmd_synth)

    p = sub.add_parser("calibrate", parents=common, help="rig extrinsics from a recording of a ChArUco or checkerboard board")
    if command == "calibrate":
        from intercap.calib.options import add_calibrate_arguments

        add_calibrate_arguments(p)
    p.set_defaults(func=_cmd_calibrate)

    p = sub.add_parser("board", parents=common, help="write the calibration board to print at its true size (PDF or PNG)")
    if command == "board":
        from intercap.calib.options import add_print_arguments

        add_print_arguments(p)
    p.set_defaults(func=_cmd_board)
    return parser


def setup_logging(verbose: bool, quiet: bool) -> None:
    """Console logging: DEBUG with -v, WARNING and up with -q, else INFO. The root logger lets INFO
    through even with -q, so OUT/run.log (`pipeline.run_log`) still gets it."""
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    root = logging.getLogger()
    ours = [h for h in root.handlers if getattr(h, "intercap_console", False)]
    if not root.handlers or ours:  # as basicConfig: handlers someone else set up are theirs
        handler = ours[0] if ours else logging.StreamHandler()
        handler.setStream(sys.stderr)  # the stream of now (a test, a redirected run)
        handler.intercap_console = True
        handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
        handler.setLevel(level)
        if not ours:
            root.addHandler(handler)
    root.setLevel(min(level, logging.INFO))


def show_progress(args) -> bool:
    """Progress bars only on a terminal (tqdm's carriage returns spoil logs and pipes) and not with -q."""
    return not args.log_quiet and sys.stderr.isatty()


def main(argv: list[str] | None = None) -> int:
    given = sys.argv[1:] if argv is None else argv
    args = build_parser(next((a for a in given if not a.startswith("-")), None)).parse_args(argv)
    args.log_verbose = getattr(args, "log_verbose", False)
    args.log_quiet = getattr(args, "log_quiet", False)
    if args.log_verbose and args.log_quiet:
        print(f"intercap {args.command}: error: -v and -q together; choose one", file=sys.stderr)
        return 2
    setup_logging(args.log_verbose, args.log_quiet)
    from intercap.config import ConfigError
    from intercap.pipeline import StageError
    from intercap.session import SessionError

    try:
        return args.func(args)
    except SessionError as exc:  # lists every problem found
        print(f"intercap {args.command}: {exc}", file=sys.stderr)
        return 2
    except FileNotFoundError as exc:
        print(f"intercap {args.command}: error: {os_error_line(exc)}", file=sys.stderr)
        return 2
    except (ConfigError, StageError, ValueError) as exc:
        print(f"intercap {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a full disk, a read-only or unwritable folder, a file where a folder goes
        print(f"intercap {args.command}: error: {os_error_line(exc)}", file=sys.stderr)
        return 1
    except Exception as exc:  # noqa: BLE001 - a bug: one line and where its traceback is, not the traceback
        if args.log_verbose:
            raise
        from intercap.batch import one_line

        print(f"intercap {args.command}: unexpected error: {one_line(exc)} ({traceback_hint()})", file=sys.stderr)
        return 1


def os_error_line(exc: OSError) -> str:
    """`path: cause` of an OSError (`No space left on device`, `Read-only file system`, ...)."""
    cause = exc.strerror or str(exc)
    if exc.filename is None:
        return cause
    return f"{exc.filename}: {cause}" + (f" (to {exc.filename2})" if exc.filename2 else "")


def traceback_hint() -> str:
    """Where the traceback of the exception being handled was written (a log file in the temporary
    folder), or, when it cannot be written, how to see it."""
    import tempfile
    import traceback

    try:
        fd, path = tempfile.mkstemp(prefix="intercap-error-", suffix=".log")
        with os.fdopen(fd, "w") as f:
            f.write(" ".join(sys.argv) + "\n" + traceback.format_exc())
    except OSError:
        return "rerun with -v for the traceback"
    return f"traceback in {path}; -v prints it"


if __name__ == "__main__":
    sys.exit(main())
