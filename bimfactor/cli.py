"""The `bimfactor` command: parses arguments, calls library functions, prints results, maps errors to exit codes.

Heavy libraries (ifcopenshell, torch, open3d) are imported inside the commands so that `--help` stays fast.
Every error bimfactor raises on purpose becomes one line `error: <message>` on stderr and the error's exit
code (2 for bad input or configuration); anything else is `error: internal: ...` with exit code 1, and
`--debug` (or BIMFACTOR_DEBUG=1) adds the traceback. A closed stdout (`| head`) ends the command quietly with 141.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import logging
import math
import os
import signal
import sys
import time
import traceback
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import click
import typer
import typer.core

from bimfactor import __version__
from bimfactor.errors import BimfactorError, ConfigError, InputError

if TYPE_CHECKING:
    from bimfactor.bim.ifc import IfcModel
    from bimfactor.bim.prior import BimPrior
    from bimfactor.config import Config

log = logging.getLogger(__name__)


try:  # typer >= 0.20 parses arguments with its own copy of click
    from typer._click import exceptions as click_exceptions
except ImportError:  # pragma: no cover - older typer runs on click itself
    from click import exceptions as click_exceptions


class _OneLineUsageError(click_exceptions.UsageError):
    """A usage error shown as one `error:` line (click prints the usage block and a hint otherwise)."""

    def show(self, file: Any = None) -> None:
        command = f"{self.ctx.command_path}: " if self.ctx is not None else ""
        typer.echo(f"error: {command}{_one_line(self.format_message())} (see --help)", err=True)


class _OneLineGroup(typer.core.TyperGroup):
    """The command group: argument parsing errors of every subcommand become one line on stderr, exit 2."""

    def make_context(self, info_name: str | None, args: list[str], *rest: Any, **kwargs: Any) -> Any:
        with _one_line_usage():
            _refuse_empty_paths(args)
            return super().make_context(info_name, args, *rest, **kwargs)

    def invoke(self, ctx: Any) -> Any:
        with _one_line_usage():
            return super().invoke(ctx)


PATH_OPTIONS = ("-o", "--output", "-c", "--config")
"""Options whose empty value is refused as such: click turns '' into '.', which would be reported as another
problem (a non-empty folder, a folder given as a config)."""


def _refuse_empty_paths(args: list[str]) -> None:
    for k, arg in enumerate(args):
        empty = arg in PATH_OPTIONS and k + 1 < len(args) and not args[k + 1].strip()
        if empty or any(arg == f"{option}=" for option in PATH_OPTIONS if option.startswith("--")):
            raise click_exceptions.UsageError(f"{arg.rstrip('=')} is empty: give a folder or file name")


@contextlib.contextmanager
def _one_line_usage() -> Iterator[None]:
    try:
        yield
    except (click_exceptions.NoArgsIsHelpError, _OneLineUsageError):
        raise
    except click_exceptions.UsageError as exc:
        raise _OneLineUsageError(exc.format_message(), exc.ctx) from None


app = typer.Typer(
    name="bimfactor",
    cls=_OneLineGroup,
    help="Robot localization against a building's BIM model (IFC): CoarseBIMLoc with pose graphs and ICP.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    rich_markup_mode=None,
    context_settings={"help_option_names": ["-h", "--help"]},
)
bench_app = typer.Typer(
    cls=_OneLineGroup,
    help="Benchmarks that anyone can rerun; each writes results.json and config.yaml to its output folder.",
    short_help="Benchmarks (results.json + config.yaml per run).",
    no_args_is_help=True,
    rich_markup_mode=None,
)
app.add_typer(bench_app, name="bench")

DEFAULT_DEMO_OUT = Path("runs/demo")
DEFAULT_PRIOR_ROOT = Path("runs/prior")
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
SIGPIPE_EXIT = 141  # 128 + SIGPIPE, what a shell reports for `yes | head`

# ------------------------------------------------------------------------------------------ common options

ConfigOption = Annotated[
    str | None,
    typer.Option(
        "--config",
        "-c",
        metavar="PRESET_OR_FILE",
        help="paper, default, fast, or a YAML file: the paper's filter alone, the recommended pipeline (default), "
        "the fewest milliseconds per keyframe, or your own overrides; merged over the defaults.",
    ),
]
DetectionsOption = Annotated[
    Path | None,
    typer.Option(
        "--detections",
        metavar="FILE",
        help="A detector's detections of the frames (JSON Lines, docs/perception.md), for this run instead of "
        "SEQ_DIR/detections.jsonl or the simulator's.",
    ),
]
IntrinsicsOption = Annotated[
    str | None,
    typer.Option(
        "--intrinsics",
        metavar="FX,FY,CX,CY",
        help="A TUM folder's colour-camera intrinsics in pixels, instead of the Freiburg camera the folder's name "
        "suggests.",
    ),
]
SetOption = Annotated[
    list[str] | None,
    typer.Option(
        "--set",
        metavar="KEY.PATH=VALUE",
        help="Override one config field (repeatable), e.g. --set bim.grid.resolution_m=0.1.",
    ),
]
BenchVariantsOption = Annotated[
    list[str] | None,
    typer.Option(
        "--variant",
        metavar="NAME",
        help="smcl, smcl+graph, refine or full (repeatable; default: the config's evaluation.variants).",
    ),
]
ScenarioOption = Annotated[
    str | None,
    typer.Option(
        "--scenario",
        metavar="NAME",
        help="global (the paper: from the uniform belief), guess (from a pose guess off the truth), kidnap "
        "(carried to another route mid-run) or active (following the localizer's suggestions, beside the passive "
        "route: variants +active) or storeys (routes that change floor, without and with the storey-change event: "
        "variants +event); default: the config's evaluation.scenario.",
    ),
]
PriorDirArgument = Annotated[Path, typer.Argument(metavar="PRIOR_DIR", help="A prior folder (bimfactor prior).")]
SequenceDirArgument = Annotated[Path, typer.Argument(metavar="SEQ_DIR", help="A sequence folder.")]
OutputOption = Annotated[Path, typer.Option("--output", "-o", metavar="OUT", help="Output folder.")]
SequenceOutputOption = Annotated[
    Path, typer.Option("--output", "-o", metavar="SEQ_DIR", help="Sequence folder to write.")
]
OverwriteOption = Annotated[bool, typer.Option("--overwrite", help="Replace an existing sequence folder.")]
VerboseOption = Annotated[bool, typer.Option("--verbose", "-v", help="Log progress (INFO); default is WARNING.")]
DebugOption = Annotated[
    bool,
    typer.Option("--debug", envvar="BIMFACTOR_DEBUG", help="Show the traceback of an error (or BIMFACTOR_DEBUG=1)."),
]
# The simulation benchmarks' building: a prior folder, or the paper-floor preset built into OUT (`_bench_world`).
BenchPriorOption = Annotated[
    Path | None,
    typer.Option("--prior", metavar="PRIOR_DIR", help="A prior folder (default: the paper-floor preset)."),
]
ForceOption = Annotated[
    bool,
    typer.Option(
        "--force", help="Localize even when the sequence says it was recorded in another building than the prior's."
    ),
]
SeedOption = Annotated[int | None, typer.Option("--seed", metavar="S", help="Seed (default: the config's).")]
RerunOption = Annotated[
    Path | None,
    typer.Option(
        "--rerun",
        metavar="FILE.rrd",
        help="Also write a Rerun recording of every keyframe (the viz extra; open it with bimfactor view FILE.rrd).",
    ),
]
InitialPoseOption = Annotated[
    str | None,
    typer.Option(
        "--initial-pose",
        metavar="X,Y,YAW_DEG[,STOREY]",
        help="Start from a pose guess in the BIM's frame (m, m, degrees), AMCL-style: particles from a Gaussian "
        "of smcl.start.sigma_xy_m / sigma_yaw_deg about it. Default: uniform over the building.",
    ),
]
StoreyOption = Annotated[
    int | None,
    typer.Option(
        "--storey",
        metavar="N",
        min=0,
        help="The storey the robot is known to start on (an elevator tells it): without --initial-pose the start is "
        "uniform over that storey only (smcl.start.storeys).",
    ),
]


def _one_line(text: str) -> str:
    return " ".join(part.strip() for part in str(text).splitlines() if part.strip()) or "(no message)"


def _fail(message: str, exit_code: int) -> typer.Exit:
    typer.echo(f"error: {_one_line(message)}", err=True)
    return typer.Exit(exit_code)


class _Terminated(BaseException):
    """SIGTERM (`timeout`, `docker stop`, systemd) or SIGHUP (the terminal closed), raised in the command so that its
    outputs are cleaned up; `signum` says which."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


TERMINATING = {signal.SIGTERM: "terminated", signal.SIGHUP: "hung up"}
"""The signals that end a command as Ctrl-C does, and the error line each gives (exit 128 + the signal)."""


def _on_terminate(signum: int, frame: Any) -> None:
    if os.getpid() != _MAIN_PID:  # a worker process of a benchmark pool: end as the default handler would
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)
        return
    raise _Terminated(signum)


_MAIN_PID = os.getpid()
PLACE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.ENAMETOOLONG, errno.ELOOP, errno.EBUSY})
"""Errors of the place written to (a full disk or quota, a read-only file system, a name too long, a loop of links, a
busy mount): the user's to fix, so one line naming the path and exit 2, not an internal error."""


@contextlib.contextmanager
def _cli_errors(debug: bool) -> Iterator[None]:
    """Turn exceptions into one `error:` line on stderr and an exit code; tracebacks only with --debug.

    SIGTERM and SIGHUP are handled like Ctrl-C: temporary outputs are removed and nothing half-written is left.
    """
    global _MAIN_PID
    _MAIN_PID = os.getpid()
    with contextlib.suppress(ValueError):  # only the main thread may set handlers (CliRunner in a thread)
        for signum in TERMINATING:
            signal.signal(signum, _on_terminate)
    try:
        yield
    except (
        typer.Exit,
        typer.Abort,
        click_exceptions.ClickException,
        click.exceptions.Exit,
        click.ClickException,
        click.Abort,
    ):
        raise
    except BimfactorError as exc:
        if debug:
            traceback.print_exc(file=sys.stderr)
        raise _fail(str(exc), exc.exit_code) from None
    except KeyboardInterrupt:
        raise _fail("interrupted", 130) from None
    except _Terminated as exc:
        raise _fail(TERMINATING[signal.Signals(exc.signum)], 128 + exc.signum) from None
    except BrokenPipeError:
        # The reader of stdout went away (`bimfactor ... | head`): files are already written atomically, so stop
        # quietly with the shell's SIGPIPE status, and point stdout at /dev/null so the exit flush cannot fail again.
        with contextlib.suppress(OSError, ValueError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        raise typer.Exit(SIGPIPE_EXIT) from None
    except OSError as exc:
        if debug:
            traceback.print_exc(file=sys.stderr)
        if exc.errno not in PLACE_ERRNOS:
            raise _fail(f"internal: {type(exc).__name__}: {exc}", 1) from None
        where = f"{exc.filename}: " if exc.filename else ""
        raise _fail(f"{where}{exc.strerror or os.strerror(exc.errno)}", 2) from None
    except Exception as exc:
        if debug:
            traceback.print_exc(file=sys.stderr)
        raise _fail(f"internal: {type(exc).__name__}: {exc}", 1) from None


_HANDLER_MARK = "_bimfactor_cli"


class _CurrentStderrHandler(logging.StreamHandler):
    """Writes to whatever `sys.stderr` is at emit time, so a caller that swaps stderr (a test runner, a notebook)
    and closes its buffer afterwards does not leave a handler writing to a closed file."""

    @property
    def stream(self):  # type: ignore[override]
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


def _setup_logging(verbose: bool) -> None:
    """Log to the current stderr: bimfactor at INFO with -v, everything else at WARNING."""
    root = logging.getLogger()
    for handler in list(root.handlers):
        if getattr(handler, _HANDLER_MARK, False):
            root.removeHandler(handler)
    handler = _CurrentStderrHandler()
    setattr(handler, _HANDLER_MARK, True)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root.addHandler(handler)
    root.setLevel(logging.WARNING)
    logging.getLogger("bimfactor").setLevel(logging.INFO if verbose else logging.WARNING)
    logging.captureWarnings(True)


def _start(config: str | None, overrides: list[str] | None, verbose: bool) -> Config:
    from bimfactor.config import load_config

    _setup_logging(verbose)
    _one_blas_thread()
    return load_config(config, overrides or [])


def _one_blas_thread() -> None:
    """Run BLAS and OpenMP on one thread, so that results do not depend on the machine's core count (a threaded BLAS
    sums in another order; measured in docs/reliability.md). The environment variables reach the libraries loaded
    later, threadpoolctl limits those already loaded; a user's own setting wins."""
    for variable in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(variable, "1")
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=int(os.environ["OPENBLAS_NUM_THREADS"]))


def _version_callback(value: bool) -> None:
    if not value:
        return
    from importlib import metadata

    lines = [f"bimfactor {__version__}"]
    # Import the compiled dependencies: a version only counts if its native library loads.
    for module in ("ifcopenshell", "open3d", "gtsam"):
        try:
            imported = __import__(module)
            version = getattr(imported, "__version__", None) or getattr(imported, "version", None)
            lines.append(f"  {module} {version or metadata.version(module)}")
        except Exception as exc:
            lines.append(f"  {module}: cannot import ({type(exc).__name__}: {_one_line(str(exc))})")
    for dist in ("torch", "sentence-transformers"):
        try:
            lines.append(f"  {dist} {metadata.version(dist)}")
        except metadata.PackageNotFoundError:
            lines.append(f"  {dist}: not installed")
    typer.echo("\n".join(lines))
    raise typer.Exit(0)


@app.callback()
def main(
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_version_callback, is_eager=True, help="Print versions (incl. compiled deps)."
        ),
    ] = False,
) -> None:
    """Robot localization against a building's BIM model (IFC).

    \b
    Examples:
      bimfactor demo
      bimfactor synth --preset office --seed 3 -o office.ifc
      bimfactor prior model.ifc -o runs/prior/model
      bimfactor bench speed
    """


# ------------------------------------------------------------------------------------------ config


@app.command("config", short_help="Print the resolved configuration: the essential keys, or every key.")
def config_cmd(
    all_keys: Annotated[
        bool, typer.Option("--all", help="Every key (expert keys too), as YAML that `-c` reads back.")
    ] = False,
    config: ConfigOption = None,
    overrides: SetOption = None,
    debug: DebugOption = False,
) -> None:
    """Print the configuration a command would run with, after the preset (-c) and the overrides (--set).

    Without --all: the essential keys (the robot, the sensor, the detector, the start, the variant), one
    `key: value  # what it means` line each, in the dotted form `--set` takes. With --all: the whole tree as YAML.

    \b
    Examples:
      bimfactor config
      bimfactor config -c paper
      bimfactor config --all --set smcl.num_particles=5000 > my.yaml && bimfactor demo -c my.yaml
    """
    with _cli_errors(debug):
        cfg = _start(config, overrides, verbose=False)
        if all_keys:
            typer.echo(cfg.dump_yaml(), nl=False)
            return
        from bimfactor.config import ESSENTIAL_KEYS, leaf_keys, value_at

        fields = dict(leaf_keys())
        rows = [(f"{key}: {json.dumps(value_at(cfg, key), ensure_ascii=False)}", key) for key in ESSENTIAL_KEYS]
        width = max(len(text) for text, _ in rows)
        for text, key in rows:
            description = " ".join((fields[key].description or "").split())
            typer.echo(f"{text:<{width}}  # {description}")


# ------------------------------------------------------------------------------------------ synth


@app.command(short_help="Write a procedural IFC4 building (paper-floor, office, multi-storey).")
def synth(
    output: Annotated[Path, typer.Option("--output", "-o", metavar="FILE.ifc", help="IFC file to write.")],
    preset: Annotated[
        str,
        typer.Option("--preset", "-p", metavar="NAME", help="Building preset: paper-floor, office or multi-storey."),
    ] = "paper-floor",
    seed: Annotated[
        int | None, typer.Option("--seed", metavar="N", help="Layout seed (default: the config's seed).")
    ] = None,
    config: ConfigOption = None,
    overrides: SetOption = None,
    verbose: VerboseOption = False,
    debug: DebugOption = False,
) -> None:
    """Write a procedural IFC4 building and print its rooms and objects.

    The same preset and seed always give a byte-identical file.

    \b
    Examples:
      bimfactor synth -o paper-floor.ifc
      bimfactor synth --preset multi-storey --seed 7 -o house.ifc
    """
    with _cli_errors(debug):
        cfg = _start(config, overrides, verbose)
        from bimfactor.bim.synth import check_synth_output, write_building

        check_synth_output(output)
        used_seed = cfg.seed if seed is None else seed
        spec = write_building(preset, used_seed, output)
        counts = spec.object_counts()
        rooms = [room for storey in spec.storeys for room in storey.rooms]
        typer.echo(f"wrote {output}: preset {preset}, seed {used_seed}")
        typer.echo(f"  storeys: {len(spec.storeys)}")
        typer.echo(f"  rooms:   {len(rooms)}")
        typer.echo(f"  objects: {sum(counts.values())} in {len(counts)} categories (doors and windows included)")
        typer.echo("    " + ", ".join(f"{name} {n}" for name, n in sorted(counts.items(), key=lambda kv: -kv[1])))


# ------------------------------------------------------------------------------------------ prior


@app.command(short_help="Build the BIM prior of an IFC file (or summarise a saved prior).")
def prior(
    model: Annotated[
        Path, typer.Argument(metavar="MODEL", help="An IFC file to build from, or a prior folder to summarise.")
    ],
    output: Annotated[
        Path | None,
        typer.Option("--output", "-o", metavar="DIR", help="Prior folder to write (default: runs/prior/<IFC name>)."),
    ] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the summary as JSON.")] = False,
    config: ConfigOption = None,
    overrides: SetOption = None,
    verbose: VerboseOption = False,
    debug: DebugOption = False,
) -> None:
    """Build the BIM prior (storey/room/object graph, grids, floor plans) from an IFC file.

    The folder gets prior.json, arrays.npz, config.yaml (the resolved config) and floorplan_<storey>.png.
    Given a prior folder instead of an IFC file, it prints that prior's summary.

    \b
    Examples:
      bimfactor prior ../shared/data/ifc/AC20-FZK-Haus.ifc -o runs/prior/fzk-haus
      bimfactor prior model.ifc -o out --set bim.grid.resolution_m=0.1 --json
      bimfactor prior runs/prior/fzk-haus
    """
    with _cli_errors(debug):
        cfg = _start(config, overrides, verbose)
        from bimfactor.bim.prior import BimPrior, build_prior, ensure_prior_destination

        if not model.exists():
            raise InputError(f"no such file or folder: {model}")
        if model.is_dir():
            if not (model / "prior.json").is_file():
                raise InputError(f"{model}: a folder but not a bimfactor prior (no prior.json); give an .ifc file")
            if output is not None:
                raise InputError(f"{model} is a prior folder, which is summarised; -o applies to IFC input only")
            built, out_dir = BimPrior.load(model), model
        else:
            if model.suffix.lower() != ".ifc":
                raise InputError(f"{model}: expected an .ifc file or a prior folder")
            out_dir = output if output is not None else DEFAULT_PRIOR_ROOT / model.stem
            ensure_prior_destination(out_dir, model)
            started = time.perf_counter()
            built = build_prior(model, cfg)
            from bimfactor.evaluation.plots import save_floorplans

            built.save(out_dir, config_yaml=cfg.dump_yaml(), extra_files=save_floorplans)
            log.info("prior built and saved in %.1f s", time.perf_counter() - started)
        summary = _prior_summary(built, out_dir)
        if as_json:
            typer.echo(json.dumps(summary, indent=2, ensure_ascii=False))
        else:
            typer.echo(_format_prior_summary(built, summary))


def _prior_summary(built: BimPrior, out_dir: Path) -> dict[str, Any]:
    """`BimPrior.summary()` plus the room list and the files written."""
    summary: dict[str, Any] = dict(built.summary())
    neighbours = _room_neighbours(built)
    summary["room_list"] = [
        {
            "id": room.id,
            "storey": room.storey_index,
            "category": room.category,
            "category_score": round(room.category_score, 3),
            "space_name": room.space_name,
            "source": room.source,
            "area_m2": round(room.area_m2, 2),
            "objects": len(room.object_ids),
            "doors_to": neighbours.get(room.id, []),
        }
        for room in built.rooms
    ]
    summary["output_dir"] = str(out_dir)
    summary["floorplans"] = [str(p) for p in sorted(Path(out_dir).glob("floorplan_*.png"))]
    return summary


def _room_neighbours(built: BimPrior) -> dict[int, list[str]]:
    """Room id → where its connecting doors and passages lead ('#<room id>' or 'outside')."""
    from bimfactor.bim.rooms import OUTSIDE

    out: dict[int, list[str]] = {}
    for door in built.doors:
        if not door.connects:
            continue
        for here, there in ((door.room_a, door.room_b), (door.room_b, door.room_a)):
            if here >= 0:
                out.setdefault(here, []).append("outside" if there == OUTSIDE else f"#{there}")
    return {rid: sorted(set(v), key=lambda s: (s == "outside", len(s), s)) for rid, v in out.items()}


def _format_prior_summary(built: BimPrior, summary: dict[str, Any]) -> str:
    lines = [f"prior of {summary['source']} ({summary['schema']}) in {summary['output_dir']}"]
    storeys = summary["storeys"]
    lines.append(f"storeys: {len(storeys)}")
    for index, st in enumerate(storeys):
        passages = f"  {st['passages']:3d} passages" if "passages" in st else ""
        lines.append(
            f"  {index}  {st['name'] or '(unnamed)':<20} {st['elevation_m']:+7.2f} m  "
            f"{st['rooms']:3d} rooms  {st['doors']:3d} doors{passages}  {st['objects']:4d} objects"
            + (f"  ({st['floor']})" if st.get("floor") else "")
        )
    lines.append(f"rooms: {summary['rooms']}  (types: {_counts(summary['room_types'])})")
    for room in summary["room_list"]:
        name = f'"{room["space_name"]}"' if room["space_name"] else ""
        doors_to = ", ".join(room["doors_to"]) or "-"
        lines.append(
            f"  #{room['id']:<3d} storey {room['storey']}  {room['category']:<16} {room['area_m2']:7.1f} m²  "
            f"{room['objects']:3d} objects  {room['source']:<9} {name:<24} opens to: {doors_to}"
        )
    passages = f"; leafless passages: {summary['passages']}" if "passages" in summary else ""
    lines.append(f"doors: {summary['doors']}, {summary['doors_connecting']} connect two places{passages}")
    portals = [f"{p['kind']} ({p['ifc_class']}) storeys {'-'.join(map(str, p['storeys']))}" for p in summary["portals"]]
    lines.append(f"portals between floors: {'; '.join(portals) if portals else 'none'}")
    lines.append(f"objects: {summary['objects']}  ({_counts(summary['objects_per_category'])})")
    if summary["ifcspace_match"]:
        threshold = built.room_matches[0].threshold if built.room_matches else float("nan")
        parts = [
            f"storey {m['storey']}: {round(m['matched_share'] * m['spaces'])}/{m['spaces']} "
            f"({100 * m['matched_share']:.0f}%)"
            for m in summary["ifcspace_match"]
        ]
        lines.append(f"IfcSpace rooms matched by flood fill (IoU ≥ {threshold:g}): " + ", ".join(parts))
    else:
        lines.append("IfcSpace rooms matched by flood fill: the model has no IfcSpace")
    timings = summary["timings_s"]
    if timings:
        total = sum(timings.values())
        lines.append("timings: " + ", ".join(f"{k} {v:.2f} s" for k, v in timings.items()) + f"; total {total:.1f} s")
    if summary["floorplans"]:
        lines.append("floor plans: " + ", ".join(summary["floorplans"]))
    return "\n".join(lines)


def _counts(counts: dict[str, int]) -> str:
    return ", ".join(f"{name} {n}" for name, n in counts.items()) or "none"


# ------------------------------------------------------------------------------------------ demo


@app.command(short_help="Run the demo: paper-floor building → prior → simulated drive → localization → a suggestion.")
def demo(
    output: OutputOption = DEFAULT_DEMO_OUT,
    rerun: RerunOption = None,
    config: ConfigOption = None,
    overrides: SetOption = None,
    verbose: VerboseOption = False,
    debug: DebugOption = False,
) -> None:
    """Run the end-to-end demo on the procedural "paper-floor" building.

    Steps: synth (OUT/paper-floor.ifc, seed from the config), prior (OUT/prior/ with floor plans), simulate
    (OUT/sequence/, trajectory 0), localize (OUT/localize/ with metrics and figures; with --rerun FILE.rrd also a
    Rerun recording of it) and suggest (a short route on OUT/office.ifc, whose offices are alike, driven until the
    split belief has a suggestion of where to look next: OUT/suggest/suggestion.json and suggestion.png).
    OUT/config.yaml holds the resolved config.

    \b
    Examples:
      bimfactor demo
      bimfactor demo -o runs/demo-seed3 --set seed=3
      bimfactor demo --rerun runs/demo.rrd
    """
    with _cli_errors(debug):
        cfg = _start(config, overrides, verbose)
        from bimfactor.demo import STEPS, run_demo
        from bimfactor.evaluation.viewer import check_recording

        check_recording(rerun, output)

        def report(index: int, step_name: str, seconds: float, message: str) -> None:
            typer.echo(f"[{index + 1}/{len(STEPS)}] {step_name}: {message} ({seconds:.1f} s)")

        result = run_demo(cfg, output, on_step=report, rerun=rerun)
        typer.echo(f"outputs in {output}/ (resolved config: {output / 'config.yaml'})")
        for figure in result.figures:
            typer.echo(f"  figure: {figure}")
        if rerun is not None:
            typer.echo(f"  Rerun recording: {rerun} (bimfactor view {rerun})")


@app.command(short_help="Open Rerun recordings (--rerun) in the viewer, or print the command that opens them.")
def view(
    target: Annotated[
        Path, typer.Argument(metavar="RUN_DIR_OR_RRD", help="A .rrd file, or a folder holding .rrd files.")
    ],
    debug: DebugOption = False,
) -> None:
    """Open the Rerun recordings that --rerun wrote (localize, refine, demo; bench buildings: a folder of them) in
    the native viewer, where a display exists; elsewhere print the commands that open them: `rerun FILE.rrd` on a
    machine with a display, `rerun --web-viewer FILE.rrd` here (it serves the viewer to a browser at the address it
    prints, http://localhost:9090).

    \b
    Examples:
      bimfactor view runs/demo.rrd
      bimfactor view runs/bench-rrd
    """
    with _cli_errors(debug):
        import shlex

        from bimfactor.evaluation.viewer import has_display, open_viewer, recordings_in, viewer_commands

        files = recordings_in(target)
        if has_display():
            typer.echo("opened: " + shlex.join(open_viewer(files)))
            return
        native, web = viewer_commands(files)
        typer.echo(f"no display here; open {'it' if len(files) == 1 else 'them'} with one of:")
        typer.echo(f"  {shlex.join(native)}    (on a machine with a display)")
        typer.echo(f"  {shlex.join(web)}    (here: then browse to http://localhost:9090)")


# ------------------------------------------------------------------------------------------ sequences


@app.command(short_help="Simulate an RGB-D + odometry sequence in a prior's building.")
def simulate(
    prior_dir: PriorDirArgument,
    output: SequenceOutputOption,
    trajectory: Annotated[
        int, typer.Option("--trajectory", "-k", min=0, metavar="K", help="Standard trajectory index (0-5).")
    ] = 0,
    all_trajectories: Annotated[
        bool, typer.Option("--all", help="All standard trajectories, into SEQ_DIR/k<K>/ (the paper's protocol).")
    ] = False,
    seed: SeedOption = None,
    kidnap_to: Annotated[
        int | None,
        typer.Option(
            "--kidnap-to",
            min=0,
            metavar="J",
            help="The kidnapped robot: after evaluation.kidnap_at keyframes of K, carry it unseen by odometry to "
            "keyframe evaluation.kidnap_resume_at of trajectory J.",
        ),
    ] = None,
    overwrite: OverwriteOption = False,
    config: ConfigOption = None,
    overrides: SetOption = None,
    verbose: VerboseOption = False,
    debug: DebugOption = False,
) -> None:
    """Drive the simulated robot along standard trajectory K and write the sequence and its preview.

    The IFC file the prior was built from must still be where the prior says (its hash is checked).
    Writes SEQ_DIR (sequence.json, frames.csv, rgb/, depth/, instances/, groundtruth.txt, odometry.txt,
    config.yaml), SEQ_DIR/detections.jsonl (the sim perception backend's noisy detections, masks and embeddings in the
    format any detector can write: docs/perception.md), SEQ_DIR/preview.png (frames) and SEQ_DIR/trajectory.png (the
    drive over the floor plan).

    \b
    Examples:
      bimfactor simulate runs/demo/prior -o runs/seq0 --trajectory 0 --seed 1
      bimfactor simulate runs/demo/prior -o runs/paper-six --all
      bimfactor simulate runs/prior/duplex -o runs/duplex-asbuilt --set sim.as_built.removed_fraction=0.2
      bimfactor simulate runs/demo/prior -o runs/kidnapped --trajectory 0 --kidnap-to 3
    """
    with _cli_errors(debug):
        cfg = _start(config, overrides, verbose)
        from bimfactor.io.atomic import check_output_dir, container_dir

        used_seed = cfg.seed if seed is None else seed
        if all_trajectories and kidnap_to is not None:
            raise ConfigError("--kidnap-to carries one trajectory's robot to another: not with --all")
        count = cfg.evaluation.num_trajectories
        for name, k in (("--trajectory", trajectory), ("--kidnap-to", kidnap_to)):
            if k is not None and k >= count:
                raise ConfigError(
                    f"{name} {k}: the standard trajectories are 0-{count - 1} (evaluation.num_trajectories)"
                )
        if all_trajectories:
            check_output_dir(output, "sequences", inputs=[prior_dir])
            for k in range(count):
                check_output_dir(output / f"k{k}", "sequence", inputs=[prior_dir], replace=overwrite)
            with container_dir(output, "sequences", inputs=[prior_dir]):
                for k in range(count):
                    typer.echo(_simulate_to_disk(prior_dir, output / f"k{k}", cfg, k, used_seed, overwrite))
        else:
            check_output_dir(output, "sequence", inputs=[prior_dir], replace=overwrite)
            typer.echo(_simulate_to_disk(prior_dir, output, cfg, trajectory, used_seed, overwrite, kidnap_to))


def _simulate_to_disk(
    prior_dir: Path,
    output: Path,
    cfg: Config,
    trajectory: int,
    seed: int,
    overwrite: bool,
    kidnap_to: int | None = None,
) -> str:
    """Simulate (with `kidnap_to`, two trajectories spliced by `sim.simulate.kidnap`), write the sequence atomically,
    then its config and preview; returns a one-line account."""
    from dataclasses import replace

    import numpy as np

    from bimfactor.demo import write_simulation
    from bimfactor.embed.text import text_model_name
    from bimfactor.sim.simulate import build_world, kidnap, load_world_inputs, simulate_sequence

    prior, model = load_world_inputs(prior_dir, cfg)
    if text_model_name(cfg.embed) != prior.embedding_model:
        raise ConfigError(
            f"the prior's objects are embedded with {prior.embedding_model}, but this config embeds with "
            f"{text_model_name(cfg.embed)}: the simulated detector's labels and embeddings would not compare; "
            "simulate with the embed.* settings the prior was built with"
        )
    world = build_world(prior, model, cfg, seed)
    result = simulate_sequence(prior, model, cfg, trajectory, seed, world=world)
    meta, frames, drive = result.meta, result.frames, result.trajectory
    dense_xy, keyframes, account = drive.poses[:, :2], drive.keyframe_poses, f"trajectory {trajectory}"
    if kidnap_to is not None:
        ev = cfg.evaluation
        other = simulate_sequence(prior, model, cfg, kidnap_to, seed, world=world)
        try:
            frames = kidnap(frames, other.frames, ev.kidnap_at, ev.kidnap_resume_at)
        except ValueError as exc:
            raise ConfigError(f"evaluation.kidnap_at / kidnap_resume_at: {exc}") from None
        carried = {"to_trajectory": kidnap_to, "at": ev.kidnap_at, "resume_at": ev.kidnap_resume_at}
        meta = replace(meta, name=f"{meta.name}-kidnapped-t{kidnap_to}", extras={**meta.extras, "kidnapped": carried})
        keyframes = np.asarray([f.gt_pose for f in frames])
        dense_xy = keyframes[:, :2]
        account = f"trajectory {trajectory}, carried after keyframe {ev.kidnap_at} to trajectory {kidnap_to}"
    route = (drive.storey_index, dense_xy, keyframes)
    n_rooms, preview = write_simulation(output, prior, prior_dir, cfg, meta, frames, route, seed, overwrite)
    return (
        f"wrote {output}: {len(frames)} keyframes of {account} (seed {seed}), "
        f"{n_rooms} room{'' if n_rooms == 1 else 's'} visited; figures {preview.name}, trajectory.png"
    )


@app.command(short_help="Convert a TUM RGB-D folder or a ROS 1 / ROS 2 / MCAP bag into a bimfactor sequence.")
def convert(
    kind: Annotated[str, typer.Argument(metavar="KIND", help="tum, rosbag or sequence.")],
    source: Annotated[
        Path,
        typer.Argument(
            metavar="SOURCE",
            help="TUM RGB-D folder; ROS 1 .bag, ROS 2 bag folder, .db3 or .mcap file; or bimfactor sequence.",
        ),
    ],
    output: SequenceOutputOption,
    overwrite: OverwriteOption = False,
    all_frames: Annotated[
        bool, typer.Option("--all-frames", help="Keep every synchronised frame, not only the keyframes.")
    ] = False,
    base_frame: Annotated[
        str | None,
        typer.Option(
            "--base-frame",
            metavar="FRAME",
            help="rosbag: the robot's base frame in tf, on the floor (default io.rosbag.base_frame: base_link); the "
            "camera mount and the odometry refer to it.",
        ),
    ] = None,
    camera_mount: Annotated[
        str | None,
        typer.Option(
            "--camera-mount",
            metavar="X,Y,Z,ROLL,PITCH,YAW",
            help="rosbag, tum: the camera mount (a bag's: instead of its tf; a TUM folder's: instead of a level "
            "camera at the base's origin): the camera's position in the base frame "
            "(metres) and the roll, pitch, yaw (degrees, about the base's x, y, z axes in that order) of its body "
            "frame (x forward, y left, z up, as a ROS camera_link). 0,0,0 looks straight ahead and a positive pitch "
            "looks down; the images' optical frame (x right, y down, z forward) is fixed to the body frame.",
        ),
    ] = None,
    odometry_source: Annotated[
        str,
        typer.Option(
            "--odometry",
            metavar="auto|rgbd|none",
            help="auto: the recording's odometry, or RGB-D odometry from its frames when it has none; rgbd: RGB-D "
            "odometry even when it has some; none: keep every frame without odometry (localize refuses it).",
        ),
    ] = "auto",
    intrinsics_text: IntrinsicsOption = None,
    detections: Annotated[
        Path | None,
        typer.Option(
            "--detections",
            metavar="FILE",
            help="A detector's detections of the recording's colour frames (JSON Lines, docs/perception.md), checked "
            "and stored in the sequence; lines of frames the keyframe selection leaves out are left out.",
        ),
    ] = None,
    config: ConfigOption = None,
    overrides: SetOption = None,
    verbose: VerboseOption = False,
    debug: DebugOption = False,
) -> None:
    """Read a recording (a bag's topics found by message type, or named in the config's io.rosbag; or a bimfactor
    sequence, to keep its keyframes at another spacing) and write it as a bimfactor sequence.

    A bag's camera mount comes from /tf_static and /tf (base frame → the colour images' frame), its intrinsics and
    lens distortion from CameraInfo (images are undistorted, depth registered to colour where it is not), its
    odometry from nav_msgs/Odometry or the odom → base transform on /tf, interpolated at each colour image. What
    the conversion found and assumed is printed and kept in sequence.json's extras.

    A recording with odometry keeps its keyframes: the first frame, then each frame whose odometry has moved
    localization.keyframe_distance_m or turned keyframe_angle_deg from the last one kept, the spacing the
    localizer's per-step motion noise is made for (--all-frames keeps every frame). A recording without odometry
    (TUM RGB-D) keeps every frame; localize needs odometry and refuses it.

    \b
    Examples:
      bimfactor convert tum rgbd_dataset_freiburg1_room -o runs/fr1-room
      bimfactor convert rosbag my_bag -o runs/bag
      bimfactor convert rosbag run.bag -o runs/bag --base-frame base_footprint --set io.rosbag.odom_topic=/wheel/odom
      bimfactor convert rosbag run.mcap -o runs/bag --camera-mount 0.15,0,0.35,0,10,0
      bimfactor convert sequence runs/bag-all -o runs/bag-1m --set localization.keyframe_distance_m=1.0
    """
    with _cli_errors(debug):
        frame_override = [] if base_frame is None else [f"io.rosbag.base_frame={json.dumps(base_frame)}"]
        cfg = _start(config, [*(overrides or []), *frame_override], verbose)
        from bimfactor.workflows import convert_recording

        if kind not in ("tum", "rosbag", "sequence"):
            raise InputError(f"unknown recording kind '{kind}' (expected tum, rosbag or sequence)")
        if kind != "rosbag" and base_frame is not None:
            raise InputError(f"--base-frame applies to rosbag recordings, not to {kind}")
        if kind == "sequence" and camera_mount is not None:
            raise InputError("--camera-mount applies to rosbag and tum recordings, not to a sequence")
        if odometry_source not in ("auto", "rgbd", "none"):
            raise InputError(f"--odometry {odometry_source}: expected auto, rgbd or none")
        if kind != "tum" and intrinsics_text is not None:
            raise InputError(f"--intrinsics applies to tum folders, not to {kind} (a bag's come from CameraInfo)")
        done = convert_recording(
            kind,
            source,
            output,
            cfg,
            overwrite=overwrite,
            all_frames=all_frames,
            camera_mount=None if camera_mount is None else _camera_mount(camera_mount),
            odometry=odometry_source,
            intrinsics=None if intrinsics_text is None else _tum_intrinsics(intrinsics_text, source),
            detections=detections,
        )
        typer.echo(
            f"wrote {output}: {done.kept} from {kind} {source}; preview {output / 'preview.png'}, mount and odometry "
            f"{output / 'checks.png'}"
        )
        for line in done.report:
            typer.echo(f"  {line}")


def _tum_intrinsics(text: str, folder: Path) -> Any:
    """`--intrinsics FX,FY,CX,CY` as the CameraIntrinsics of the folder's images (their size from its first image)."""
    from bimfactor.io.tum_rgbd import tum_default_intrinsics, tum_image_size
    from bimfactor.types import CameraIntrinsics

    try:
        values = [float(p) for p in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise InputError(f"--intrinsics '{text}': expected FX,FY,CX,CY (four numbers, pixels)")
    default = tum_default_intrinsics(folder.name)
    width, height = tum_image_size(folder) or (default.width, default.height)
    return CameraIntrinsics(width, height, *values)


def _camera_mount(text: str) -> Any:
    """`--camera-mount X,Y,Z,ROLL,PITCH,YAW` (metres, degrees) as a (4, 4) T_base_camera."""
    from bimfactor.io.rosbag import mount_from_xyz_rpy

    try:
        values = [float(p) for p in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 6 or not all(math.isfinite(v) for v in values):
        raise InputError(f"--camera-mount '{text}': expected X,Y,Z,ROLL,PITCH,YAW (six numbers: metres, degrees)")
    return mount_from_xyz_rpy(values)


# ------------------------------------------------------------------------------------------ localize


def _variant_overrides(name: str, variants: list[str] | str | None) -> list[str]:
    """A `--variant` option as a config override of `name` (validated with the rest of the config)."""
    if not variants:
        return []
    return [f"{name}={json.dumps(variants)}"]


def _start_overrides(text: str | None, storey: int | None) -> list[str]:
    """`--initial-pose X,Y,YAW_DEG[,STOREY]` as the overrides of smcl.start.pose (and storey), and
    `--storey N` as smcl.start.storeys."""
    known = [] if storey is None else [f"smcl.start.storeys=[{storey}]"]
    if text is None:
        return known
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        values = []
    if len(values) not in (3, 4) or (len(values) == 4 and not values[3].is_integer()):
        raise InputError(f"--initial-pose '{text}': expected X,Y,YAW_DEG or X,Y,YAW_DEG,STOREY (metres, degrees)")
    on = [f"smcl.start.storey={int(values[3])}"] if len(values) == 4 else []
    return [f"smcl.start.pose={json.dumps(values[:3])}", *on, *known]


def _localize_overrides(
    overrides: list[str] | None, variant: str | None, initial_pose: str | None, storey: int | None
) -> list[str]:
    """`--set`, then `--variant` (localization.variant), `--initial-pose` and `--storey` as overrides."""
    return [
        *(overrides or []),
        *_variant_overrides("localization.variant", variant),
        *_start_overrides(initial_pose, storey),
    ]


def _protocol_config(
    config: str | None, overrides: list[str] | None, variants: list[str] | None, scenario: str | None, verbose: bool
) -> Config:
    """The config of a protocol benchmark: `--variant` and `--scenario` applied over `--set`."""
    scenario_set = [f"evaluation.scenario={scenario}"] if scenario else []
    variant_list = list(variants) if variants else None
    return _start(
        config, [*(overrides or []), *scenario_set, *_variant_overrides("evaluation.variants", variant_list)], verbose
    )


def _bench_dir(output: Path, *inputs: Path | str | None) -> contextlib.AbstractContextManager[Path]:
    """A benchmark's output folder (`io.atomic.container_dir`): new, empty or an earlier benchmark's, never an input."""
    from bimfactor.io.atomic import container_dir

    return container_dir(output, "bench", inputs=[i for i in inputs if i is not None])


def _write_bench(output: Path, name: str, result: dict[str, Any], cfg: Config) -> Path:
    """OUT/results.json ({"benchmark": name, **result}) and OUT/config.yaml, each written atomically."""
    from bimfactor.io.atomic import write_text_atomic

    results = output / "results.json"
    write_text_atomic(results, json.dumps({"benchmark": name, **result}, indent=2, default=float))
    write_text_atomic(output / "config.yaml", cfg.dump_yaml())
    return results


def _say(line: str) -> None:
    """A workflow's line: warnings to stderr, the rest to stdout."""
    typer.echo(line, err=line.startswith("warning:"))


def _metrics_line(metrics: Any) -> str:
    """One line of a run's TrajectoryMetrics."""
    return (
        f"translation {metrics.trans_err_m:.2f} ± {metrics.trans_err_std_m:.2f} m, "
        f"orientation {metrics.orient_err_deg:.1f} ± {metrics.orient_err_std_deg:.1f}°, "
        f"room accuracy {100 * metrics.room_acc:.1f} %, converged at step {metrics.steps_to_converge}, "
        f"95 % ellipse coverage {100 * metrics.ellipse95_coverage:.0f} %, step {metrics.step_ms_median:.1f} ms (median)"
    )


@app.command(short_help="Localize a sequence against a prior: semantic MCL, per-mode pose graphs, ICP (by default).")
def localize(
    prior_dir: PriorDirArgument,
    sequence_dir: SequenceDirArgument,
    output: Annotated[Path, typer.Option("--output", "-o", metavar="RUN_DIR", help="Run folder to write.")],
    variant: Annotated[
        str | None,
        typer.Option(
            "--variant",
            metavar="NAME",
            help="smcl, smcl+graph or full (default: the config's localization.variant).",
        ),
    ] = None,
    seed: SeedOption = None,
    initial_pose: InitialPoseOption = None,
    storey: StoreyOption = None,
    detections: DetectionsOption = None,
    suggest: Annotated[
        bool,
        typer.Option(
            "--suggest",
            help="End with where to look next (active localization): RUN_DIR/suggestion.json and suggestion.png.",
        ),
    ] = False,
    rerun: RerunOption = None,
    force: ForceOption = False,
    config: ConfigOption = None,
    overrides: SetOption = None,
    verbose: VerboseOption = False,
    debug: DebugOption = False,
) -> None:
    """Run perception (the config's backend; auto: the simulator's for a simulated sequence, else the detector's
    detections in SEQ_DIR/detections.jsonl or --detections FILE, else the shipped YOLOX-Nano) and the semantic
    particle filter over every frame of a sequence;
    with --variant smcl+graph the filter's modes each update a GTSAM pose graph and the most probable mode is
    the estimate; --variant full also registers each keyframe's depth scan against the BIM walls (ICP) from the
    most probable mode and feeds accepted fits into its graph.

    Writes RUN_DIR/estimate.txt (TUM), steps.csv (pose, storey, room, covariance, converged flag, number of modes
    per step, full: whether ICP was accepted; skipped: why a frame's observations were not used, for empty or
    saturated depth or an odometry jump; on a building with twin storeys the estimate's twin pose and the
    belief's weight there), modes.csv (graph variants: every mode per step), metrics.json (with
    ground truth: the paper's translation / orientation error, room accuracy and the 95 % ellipse coverage; full:
    ICP acceptance and rejection reasons), snapshots.npz, config.yaml, trajectory.png and particles.png; with
    --suggest, suggestion.json and suggestion.png: the goal (odometry frame) whose view best tells the belief's modes
    apart after the last frame, or why there is none (docs/active.md). RUN_DIR must be new, empty or an earlier run.

    \b
    Examples:
      bimfactor localize runs/demo/prior runs/demo/sequence -o runs/loc0
      bimfactor localize runs/demo/prior runs/demo/sequence -o runs/loc0-graph --variant smcl+graph
      bimfactor localize runs/demo/prior runs/demo/sequence -o runs/loc0-filter --variant smcl
      bimfactor localize runs/prior/duplex runs/duplex-k0 -o runs/loc-duplex --set smcl.num_particles=5000
      bimfactor localize runs/demo/prior runs/demo/sequence -o runs/loc0-guess --initial-pose 63.5,7.9,-97
      bimfactor localize runs/prior/ac11 runs/ac11-k2 -o runs/loc-ac11-k2 --storey 2
      bimfactor localize runs/prior/office runs/office-bag -o runs/loc-bag --detections yolo-world.jsonl
      bimfactor localize runs/prior/duplex runs/duplex-k0 -o runs/loc-duplex-next --suggest
      bimfactor localize runs/demo/prior runs/demo/sequence -o runs/loc0 --rerun runs/loc0.rrd
    """
    with _cli_errors(debug):
        cfg = _start(config, _localize_overrides(overrides, variant, initial_pose, storey), verbose)
        from bimfactor.evaluation.report import run_metrics, twin_summary
        from bimfactor.pipeline import skipped_frames_note
        from bimfactor.workflows import localize_files

        run, figures = localize_files(
            prior_dir, sequence_dir, output, cfg, seed=seed, detections=detections, suggest=suggest, force=force,
            rerun=rerun, say=_say,
        )  # fmt: skip
        n = len(run.timestamps_s)
        typer.echo(f"wrote {output}: {n} steps ({run.variant}); figures " + ", ".join(f.name for f in figures))
        if rerun is not None:
            typer.echo(f"Rerun recording: {rerun} (bimfactor view {rerun})")
        relocalized = [str(i) for i, spread in enumerate(run.relocalized) if spread]
        if relocalized:
            typer.echo(
                "the belief stopped explaining the depth scans and was spread over the building again at step(s) "
                f"{', '.join(relocalized)} (steps.csv: relocalized)"
            )
        challenged = [str(i) for i, moved in enumerate(run.challenged) if moved]
        if challenged:
            typer.echo(
                "a challenger drawn from the observations explained the frames better and the belief moved there at "
                f"step(s) {', '.join(challenged)} (steps.csv: challenged)"
            )
        skipped = skipped_frames_note(run)
        if skipped is not None:
            typer.echo(f"warning: {skipped} (steps.csv: skipped)", err=True)
        metrics = run_metrics(run)
        if metrics is not None:
            typer.echo(_metrics_line(metrics))
        twins = twin_summary(run)
        if twins is not None:
            typer.echo(twins)
        if run.suggestion is not None:
            files = "suggestion.json" if run.suggestion.goal_odom is None else "suggestion.json, suggestion.png"
            typer.echo(f"{run.suggestion.describe()} ({files})")


@app.command("scene-graph", short_help="Build the online open-set scene graph of an RGB-D recording with camera poses.")
def scene_graph(
    recording: Annotated[
        Path,
        typer.Argument(metavar="RECORDING", help="A TUM RGB-D folder with groundtruth.txt, or a sequence folder."),
    ],
    output: Annotated[Path, typer.Option("--output", "-o", metavar="OUT", help="Folder to write.")],
    intrinsics_text: IntrinsicsOption = None,
    config: ConfigOption = None,
    overrides: SetOption = None,
    verbose: VerboseOption = False,
    debug: DebugOption = False,
) -> None:
    """Build the online open-set scene graph (the paper's Sec. II.B) of a recording from its camera poses: a TUM
    RGB-D folder's motion-capture poses (6-DoF, a hand-held camera's too), or a sequence's ground-truth (else
    odometry) poses through its camera mount. Each frame is detected (perception.backend; auto: the simulator's for a
    simulated sequence, the folder's detections.jsonl, else the shipped YOLOX-Nano with COCO's class names), its
    boxes segmented by depth, lifted and fused into the graph's nodes.

    Writes OUT/scene_graph.json (each node's label, centre and extent in metres in the recording's world frame,
    observations and voxels; the edges), OUT/scene_graph.png (the nodes over the fused point cloud, from above) and
    OUT/config.yaml. OUT must be new, empty or an earlier scene graph.

    \b
    Examples:
      bimfactor scene-graph ../shared/data/real/tum-fr1-rpy -o runs/sg-tum
      bimfactor scene-graph ../shared/data/real/slambook-dining -o runs/sg-dining --intrinsics 518,519,325.5,253.5
      bimfactor scene-graph runs/demo/sequence -o runs/sg-demo
    """
    with _cli_errors(debug):
        cfg = _start(config, overrides, verbose)
        from bimfactor.evaluation.mapping import scene_graph_run

        intrinsics = None if intrinsics_text is None else _tum_intrinsics(intrinsics_text, recording)
        done = scene_graph_run(recording, output, cfg, intrinsics, show_progress=True)
        counts = Counter(node["label"] for node in done.record["nodes"])
        listing = ", ".join(f"{n} {label}" for label, n in counts.most_common())
        typer.echo(
            f"wrote {output}: {len(done.record['nodes'])} nodes from {done.record['frames_used']} frames "
            f"({done.record['detector']}, {done.record['poses']} poses): {listing or 'none'}; figure {done.figure.name}"
        )


@app.command(short_help="Localize with pose graphs, then smooth each surviving mode's whole trajectory (offline).")
def refine(
    prior_dir: PriorDirArgument,
    sequence_dir: SequenceDirArgument,
    output: Annotated[Path, typer.Option("--output", "-o", metavar="OUT", help="Run folder to write.")],
    variant: Annotated[
        str, typer.Option("--variant", metavar="NAME", help="The forward pass: smcl+graph or full.")
    ] = "smcl+graph",
    seed: SeedOption = None,
    initial_pose: InitialPoseOption = None,
    storey: StoreyOption = None,
    detections: DetectionsOption = None,
    rerun: RerunOption = None,
    force: ForceOption = False,
    config: ConfigOption = None,
    overrides: SetOption = None,
    verbose: VerboseOption = False,
    debug: DebugOption = False,
) -> None:
    """Offline refinement of a recorded sequence: the forward pass (smcl+graph, or full: with ICP against the BIM
    walls), then batch Levenberg-Marquardt smoothing of the whole trajectory of every mode that survived it (a full
    forward pass's accepted ICP fits enter as pose factors); the most probable mode is the estimate.

    Writes OUT/estimate.txt (refined, TUM), forward.txt (the forward pass, TUM), steps.csv (refined pose and
    covariance per step), modes.json and modes/NN_mode_<id>.txt (every refined mode), metrics.json (with ground
    truth: refined and forward metrics), config.yaml and trajectory.png, as one folder written atomically. OUT
    must be new, empty or an earlier run.

    \b
    Examples:
      bimfactor refine runs/demo/prior runs/demo/sequence -o runs/refine0
      bimfactor refine runs/demo/prior runs/demo/sequence -o runs/refine0-full --variant full
      bimfactor refine runs/prior/duplex runs/duplex-k0 -o runs/refine-duplex --set backend.max_modes=3
      bimfactor refine runs/demo/prior runs/demo/sequence -o runs/refine0 --rerun runs/refine0.rrd
    """
    with _cli_errors(debug):
        cfg = _start(config, _localize_overrides(overrides, variant, initial_pose, storey), verbose)
        from bimfactor.evaluation.report import run_metrics, track_metrics
        from bimfactor.workflows import refine_files

        run, refined = refine_files(
            prior_dir, sequence_dir, output, cfg, seed=seed, detections=detections, force=force, rerun=rerun, say=_say
        )
        typer.echo(
            f"wrote {output}: {len(run.timestamps_s)} steps, {len(refined.modes)} modes refined in "
            f"{refined.refine_ms:.0f} ms"
        )
        if rerun is not None:
            typer.echo(f"Rerun recording of the forward pass: {rerun} (bimfactor view {rerun})")
        if len(refined.segments) > 1:
            stretches = ", ".join(f"{steps.start}–{steps.stop - 1}" for steps in refined.segments)
            why = ["the filter relocalized"] if "relocalized" in refined.begins else []
            if refined.offline_seams:
                why.append(f"parted offline at step {', '.join(map(str, refined.offline_seams))}")
            typer.echo(f"steps {stretches} refined apart ({'; '.join(why)}; steps.csv: segment)")
        forward = run_metrics(run)
        if forward is not None:
            refined_metrics = track_metrics(refined.estimate, run.gt_poses, run.gt_rooms)
            typer.echo(f"forward ({run.variant}): {_metrics_line(forward)}")
            typer.echo(f"refined: {_metrics_line(refined_metrics)}")


# ------------------------------------------------------------------------------------------ registration


@app.command("compare-registrars", short_help="Compare fine registrars against the BIM walls (basin of convergence).")
def compare_registrars_cmd(
    prior_dir: PriorDirArgument,
    output: OutputOption,
    sequence_dir: Annotated[
        Path | None,
        typer.Argument(
            metavar="SEQ_DIR",
            help="Keyframes from this sequence with ground truth, or from the sequences inside it "
            "(default: simulate the building's standard trajectories).",
        ),
    ] = None,
    methods: Annotated[
        list[str] | None,
        typer.Option("--method", "-m", metavar="NAME", help="Registrar (repeatable; default: every installed one)."),
    ] = None,
    config: ConfigOption = None,
    overrides: SetOption = None,
    verbose: VerboseOption = False,
    debug: DebugOption = False,
) -> None:
    """Perturb keyframes of the prior's building (simulated, or from SEQ_DIR) by a sweep of initial errors
    (0-2 m, 0-30°) and run each registrar: success (< 5 cm and < 1°), final error, time, and the gate's
    acceptance and precision without the ambiguity probes, with them, and with a calibrated coarse covariance.

    Writes OUT/summary.json, OUT/records.json, OUT/basins.png and OUT/config.yaml. Registrars: point_to_plane
    (the default: Open3D coarse to fine, polished over SE(2)), planar (point-to-plane Gauss-Newton over SE(2)),
    point_to_point, robust, gicp, and small_gicp, kiss_icp when installed (pip install 'bimfactor[registrars]').

    \b
    Examples:
      bimfactor compare-registrars runs/demo/prior -o runs/compare
      bimfactor compare-registrars runs/prior/duplex -o runs/compare-duplex -m planar -m gicp
      bimfactor compare-registrars runs/prior/duplex runs/duplex-six -o runs/compare-duplex-six
    """
    with _cli_errors(debug):
        cfg = _start(config, overrides, verbose)
        from bimfactor.evaluation.registrars import format_summary_table, run_comparison

        with _bench_dir(output, prior_dir, sequence_dir):
            summary = run_comparison(prior_dir, output, cfg, list(methods) if methods else None, sequence_dir)
        typer.echo(format_summary_table(summary))
        typer.echo(f"results: {output / 'summary.json'}, figure: {output / 'basins.png'}")


# ------------------------------------------------------------------------------------------ bench


@bench_app.command("paper", short_help="The paper's protocol: 6 trajectories x 3 repeats, Table I per variant.")
def bench_paper(
    output: OutputOption = Path("runs/bench-paper"),
    ifc: Annotated[
        Path | None, typer.Option("--ifc", metavar="PATH", help="Another building (default: the paper-floor preset).")
    ] = None,
    prior_dir: BenchPriorOption = None,
    variants: BenchVariantsOption = None,
    scenario: ScenarioOption = None,
    workers: Annotated[int | None, typer.Option("--workers", min=1, help="Parallel processes (default: CPUs).")] = None,
    config: ConfigOption = None,
    overrides: SetOption = None,
    verbose: VerboseOption = False,
    debug: DebugOption = False,
) -> None:
    """Six standard trajectories (T = 50, distinct starts), each localized three times; prints Table I of each
    variant, scored over the T steps from the step the filter first reports itself converged (the paper's reading;
    --set evaluation.score_from=start: from the first frame), with the same runs' first T steps on the last line,
    and writes OUT/results.json (its keys: docs/evaluation.md), OUT/error_by_step.png and OUT/config.yaml. The
    building's prior is built into OUT/prior, or with --prior a saved one is used (as a rerun's OUT/prior). With
    --scenario kidnap the scored steps follow the kidnapping. With --set evaluation.known_storey=true each run's
    uniform start covers only the storey its route starts on.

    \b
    Examples:
      bimfactor bench paper
      bimfactor bench paper --variant smcl --variant refine -o runs/bench-paper-refine
      bimfactor bench paper --variant smcl+graph --variant full -o runs/bench-paper-full
      bimfactor bench paper --ifc ../shared/data/ifc/duplex.ifc -o runs/bench-paper-duplex
      bimfactor bench paper --prior runs/bench-paper-duplex/prior -o runs/bench-paper-duplex-kidnap --scenario kidnap
      bimfactor bench paper --scenario kidnap --variant smcl --variant smcl+graph -o runs/bench-paper-kidnap
      bimfactor bench paper --ifc ../shared/data/ifc/AC11-Institute-Var-2-IFC.ifc --set evaluation.known_storey=true
    """
    with _cli_errors(debug):
        cfg = _protocol_config(config, overrides, variants, scenario, verbose)
        from bimfactor.bim.prior import build_prior
        from bimfactor.bim.synth import write_building
        from bimfactor.evaluation.paper import check_protocol, format_tables, run_paper_bench
        from bimfactor.evaluation.plots import save_floorplans
        from bimfactor.sim.simulate import load_world_inputs

        check_protocol(cfg)
        if prior_dir is not None and ifc is not None:
            raise ConfigError("--ifc builds a prior, --prior names a saved one: give one of them")
        if prior_dir is not None:
            load_world_inputs(prior_dir, cfg)  # the prior and its IFC file, checked before OUT is made

        with _bench_dir(output, prior_dir, ifc):
            if prior_dir is None:
                if ifc is None:
                    ifc = output / "paper-floor.ifc"
                    write_building("paper-floor", cfg.seed, ifc)
                prior_dir = output / "prior"
                build_prior(ifc, cfg).save(prior_dir, config_yaml=cfg.dump_yaml(), extra_files=save_floorplans)
            report = run_paper_bench(prior_dir, cfg, output, workers=workers)
        typer.echo(format_tables(report))
        typer.echo(f"results: {output / 'results.json'}")
        if (output / "error_by_step.png").is_file():
            typer.echo(f"figure: {output / 'error_by_step.png'}")


@bench_app.command(
    "buildings", short_help="The paper's protocol over many buildings at once, on Ray: a table per building."
)
def bench_buildings(
    buildings: Annotated[
        list[Path] | None,
        typer.Argument(
            metavar="IFC",
            help="IFC files, or paper-floor for the preset (default: it and every IFC under ../shared/data/ifc).",
            show_default=False,
        ),
    ] = None,
    output: OutputOption = Path("runs/bench-buildings"),
    variants: BenchVariantsOption = None,
    scenario: ScenarioOption = None,
    runner: Annotated[
        str, typer.Option("--runner", metavar="NAME", help="ray (a local Ray instance, or --address) or processes.")
    ] = "ray",
    address: Annotated[
        str | None,
        typer.Option(
            "--address",
            metavar="ADDR",
            help="A running Ray cluster: auto, HOST:PORT or ray://HOST:PORT; its nodes need bimfactor and see OUT.",
        ),
    ] = None,
    workers: Annotated[int | None, typer.Option("--workers", min=1, help="Parallel runs (default: CPUs).")] = None,
    rerun: Annotated[
        Path | None,
        typer.Option(
            "--rerun",
            metavar="DIR",
            help="Also write a Rerun recording of each run's forward pass into DIR (viz extra; bimfactor view DIR).",
        ),
    ] = None,
    config: ConfigOption = None,
    overrides: SetOption = None,
    verbose: VerboseOption = False,
    debug: DebugOption = False,
) -> None:
    """The paper's protocol (six routes x three repeats, each scoring every variant) on every building, all runs on
    one runner: Ray by default (a local instance; --address sends them to a cluster), or a local process pool (the
    results are the same). Writes OUT/results.json (per building IFC file name, per variant: Table I's keys and
    success_rate, wrong_convergence_rate, distance_to_convergence_m, top3_rate), OUT/report.md (a table per
    building and the worst building and route), OUT/buildings.png, OUT/config.yaml and each prior under
    OUT/priors/; with --rerun DIR, DIR/<building>-t<route>-r<repeat>-<variant>.rrd for every forward pass (not in the
    active scenario). Longer routes: --set evaluation.trajectory_length=150.

    \b
    Examples:
      bimfactor bench buildings
      bimfactor bench buildings ../shared/data/ifc/duplex.ifc --variant smcl+graph -o runs/bench-duplex
      bimfactor bench buildings paper-floor ../shared/data/ifc/AC11-Institute-Var-2-IFC.ifc -o runs/bench-two
      bimfactor bench buildings --set evaluation.trajectory_length=150 -o runs/bench-buildings-150
      bimfactor bench buildings --address head:6379 -o /shared/runs/bench-buildings
      bimfactor bench buildings paper-floor --set evaluation.num_trajectories=1 --rerun runs/bench-rrd
    """
    with _cli_errors(debug):
        cfg = _protocol_config(config, overrides, variants, scenario, verbose)
        from bimfactor.bim.ifc import read_schema
        from bimfactor.evaluation.buildings import (
            PAPER_FLOOR,
            default_buildings,
            format_buildings_report,
            run_buildings_bench,
        )
        from bimfactor.evaluation.paper import (
            check_cluster,
            check_protocol,
            check_runner,
            ray_session,
            runner_description,
        )

        check_protocol(cfg)
        check_runner(runner, address)
        _check_recording_dir(rerun, cfg, output)
        # "paper-floor" (not a file of that name) is the preset, as in the default set
        given = [PAPER_FLOOR if str(b) == PAPER_FLOOR and not b.exists() else b for b in buildings or []]
        chosen: list[str | Path] = given or default_buildings()
        for building in chosen:
            if isinstance(building, Path):
                if not building.is_file():
                    raise InputError(f"no such IFC file: {building}")
                read_schema(building)  # not IFC, or truncated: refused before any prior is built
        if address is not None:
            check_cluster(address)  # a closed port: refused at once
        typer.echo(f"runs on: {runner_description(runner, address, workers)}")
        # Ray is connected before any prior is built: a cluster that does not answer costs seconds, not priors
        session = ray_session(workers, address) if runner == "ray" else contextlib.nullcontext({})
        with session as where, _bench_dir(output, *[b for b in chosen if isinstance(b, Path)]):
            if where:
                typer.echo(f"  {where['nodes']} node(s), {where['cpus']} CPUs")
            report = run_buildings_bench(chosen, cfg, output, runner, workers, address, rerun)
        typer.echo(format_buildings_report(report), nl=False)
        typer.echo(f"results: {output / 'results.json'}, report: {output / 'report.md'}")
        typer.echo(f"figure: {output / 'buildings.png'}")
        if rerun is not None:
            typer.echo(f"Rerun recordings: {rerun}/ (bimfactor view {rerun})")


def _check_recording_dir(folder: Path | None, cfg: Config, output: Path) -> None:
    """Before any run: InputError unless `folder` (None: no recordings) can hold a benchmark's Rerun recordings."""
    if folder is None:
        return
    from bimfactor.evaluation.viewer import check_outside, require_rerun

    if folder.exists() and not folder.is_dir():
        raise InputError(f"--rerun {folder}: a benchmark writes one recording per run into a folder, not a file")
    check_outside(folder, output)
    if cfg.evaluation.scenario == "active":
        raise InputError("--rerun records the forward passes of the protocol's runs; the active scenario has none")
    require_rerun()


@bench_app.command("graph", short_help="Online scene graph quality (precision, recall, segmentation) and speed.")
def bench_graph(
    building: Annotated[
        str, typer.Option("--building", metavar="PRESET_OR_IFC", help="Synth preset name or IFC path.")
    ] = "paper-floor",
    output: OutputOption = Path("runs/bench-graph"),
    preset: Annotated[str | None, typer.Option("--preset", help="Sim perception preset: clean, paper, harsh.")] = None,
    tour: Annotated[int, typer.Option("--tour", min=0, help="Orbit every furniture group with N frames instead.")] = 0,
    true_odometry: Annotated[bool, typer.Option("--true-odometry", help="Drift-free odometry (a diagnostic).")] = False,
    config: ConfigOption = None,
    overrides: SetOption = None,
    verbose: VerboseOption = False,
    debug: DebugOption = False,
) -> None:
    """Build the online graph over the standard trajectories of a building and score it against the BIM objects;
    writes OUT/report.json and one PNG of the final graph over the floor plan per sequence.

    \b
    Examples:
      bimfactor bench graph --building ../shared/data/ifc/duplex.ifc -o runs/graph-duplex
      bimfactor bench graph --building paper-floor --tour 12 -o runs/graph-tour
    """
    with _cli_errors(debug):
        cfg = _start(config, overrides, verbose)
        from bimfactor.evaluation.graph import run_graph_bench

        with _bench_dir(output, *([building] if Path(building).exists() else [])):
            result = run_graph_bench(building, cfg, output, preset, tour, true_odometry)
        summary, speed = result["summary"], result["speed"]
        typer.echo(json.dumps({"summary": summary, "speed": speed}, indent=1, default=float))
        typer.echo(f"results: {output / 'report.json'}")


def _bench_world(prior_dir: Path | None, cfg: Config) -> tuple[BimPrior, IfcModel] | None:
    """The prior and IFC model of `--prior`, loaded before OUT is made (a bad --prior leaves nothing behind); None
    for the paper-floor preset, which `_paper_floor_world` builds into OUT."""
    from bimfactor.sim.simulate import load_world_inputs

    return None if prior_dir is None else load_world_inputs(prior_dir, cfg)


def _paper_floor_world(output: Path, cfg: Config) -> tuple[BimPrior, IfcModel]:
    """The paper-floor preset written to OUT/paper-floor.ifc and built into OUT/prior, with its IFC model."""
    from bimfactor.bim.prior import build_prior
    from bimfactor.bim.synth import write_building
    from bimfactor.evaluation.plots import save_floorplans
    from bimfactor.sim.simulate import load_world_inputs

    write_building("paper-floor", cfg.seed, output / "paper-floor.ifc")
    prior = build_prior(output / "paper-floor.ifc", cfg)
    prior.save(output / "prior", config_yaml=cfg.dump_yaml(), extra_files=save_floorplans)
    return load_world_inputs(output / "prior", cfg)


def _echo_bench(output: Path, name: str, result: dict[str, Any], cfg: Config) -> None:
    """Write a benchmark's results (`_write_bench`) and print them."""
    results = _write_bench(output, name, result, cfg)
    typer.echo(json.dumps(result, indent=1, default=float))
    typer.echo(f"results: {results}")


@bench_app.command(
    "speed", short_help="Every speed figure in one table: keyframes, registrars side by side, filter, startup, prior."
)
def bench_speed(
    ifc: Annotated[
        list[Path] | None,
        typer.Option(
            "--ifc",
            metavar="PATH",
            help="IFC building timed beside the paper floor (repeatable; default: duplex.ifc from ../shared).",
        ),
    ] = None,
    output: OutputOption = Path("runs/bench-speed"),
    config: ConfigOption = None,
    overrides: SetOption = None,
    verbose: VerboseOption = False,
    debug: DebugOption = False,
) -> None:
    """Every speed figure in one table, measured in one run on this machine (bimfactor.evaluation.speedtable):
    the full variant per keyframe on the paper floor and each --ifc building (simulated trajectory 0), with the sim
    perception and with the real one (the shipped YOLOX-Nano, door plates read by RapidOCR); the fine
    registrars side by side on its keyframes (median time, ratio to Open3D point-to-plane, success over
    compare-registrars' sweep); the filter step at M = 1000 and 20000; and, each in a fresh process, bimfactor
    --help, a 50-keyframe localize, the demo and the prior of AC11-Institute-Var-2 cold and with its geometry cached.
    Writes OUT/results.json, OUT/speed.md and OUT/config.yaml. Takes several minutes.

    \b
    Examples:
      bimfactor bench speed
      bimfactor bench speed --ifc ../shared/data/ifc/AC20-FZK-Haus.ifc -o runs/bench-speed-fzk
    """
    with _cli_errors(debug):
        cfg = _start(config, overrides, verbose)
        from bimfactor.bim.prior import build_prior
        from bimfactor.evaluation.bench import find_shared_ifc_dir, shared_ifc_dir
        from bimfactor.evaluation.speedtable import (
            PRIOR_BENCH_FILE,
            filter_rows,
            format_speed_table,
            keyframe_times,
            real_frames_rows,
            real_perception_rows,
            registrar_rows,
            wall_clock_rows,
        )
        from bimfactor.io.atomic import output_dir, write_text_atomic
        from bimfactor.io.sequence import write_sequence_files
        from bimfactor.sim.simulate import load_world_inputs

        files = list(ifc) if ifc else [shared_ifc_dir() / "duplex.ifc"]
        for path in files:
            if not path.is_file():
                raise InputError(f"no such IFC file: {path}")
        shared = find_shared_ifc_dir()
        with _bench_dir(output, *files):
            rows, summaries = [], {}
            buildings = [("paper floor", None), *((path.name, path) for path in files)]
            for k, (name, path) in enumerate(buildings, 1):
                typer.echo(
                    f"[{k}/{len(buildings) + 1}] {name}: the full variant per keyframe, the registrars", err=True
                )
                if path is None:
                    prior, model = _paper_floor_world(output, cfg)
                    prior_dir = output / "prior"
                else:
                    prior_dir = output / "priors" / path.stem
                    build_prior(path, cfg).save(prior_dir, config_yaml=cfg.dump_yaml())
                    prior, model = load_world_inputs(prior_dir, cfg)
                times, frames, meta = keyframe_times(cfg, name, prior, model, cfg.seed)
                if path is None:
                    paper_prior = prior
                    with output_dir(output / "sequence", "sequence", replace=True) as folder:
                        write_sequence_files(folder, meta, frames, label=str(output / "sequence"))
                real = real_perception_rows(cfg, name, prior, frames, meta, cfg.seed)
                registrars, summaries[name] = registrar_rows(cfg, name, prior, model, frames, meta, cfg.seed)
                rows += times + real + registrars
            typer.echo(
                f"[{len(buildings) + 1}/{len(buildings) + 1}] the filter step, then commands in fresh processes",
                err=True,
            )
            rows += real_frames_rows(cfg)
            rows += filter_rows(cfg, paper_prior)
            prior_file = shared / PRIOR_BENCH_FILE if shared is not None else None
            rows += wall_clock_rows(output, output / "prior", output / "sequence", prior_file)
            table = format_speed_table(rows)
            write_text_atomic(output / "speed.md", table + "\n")
            results = _write_bench(
                output,
                "speed",
                {"rows": [dataclasses.asdict(r) | {"met": r.met} for r in rows], "registrars": summaries},
                cfg,
            )
        typer.echo(table)
        typer.echo(f"results: {results}, {output / 'speed.md'}")


@bench_app.command("scanmatch", short_help="Scan matching against the BIM: accuracy, covariance honesty, time.")
def bench_scanmatch(
    prior_dir: BenchPriorOption = None,
    output: OutputOption = Path("runs/bench-scanmatch"),
    every: Annotated[int, typer.Option("--every", min=1, help="Match every N-th simulated keyframe.")] = 2,
    config: ConfigOption = None,
    overrides: SetOption = None,
    verbose: VerboseOption = False,
    debug: DebugOption = False,
) -> None:
    """Correlative scan matching (the pose graphs' scan factor) on the evaluation's simulated keyframes from
    0.3 m / 5° perturbed starts: accepted share, errors, 95 % coverage of its covariance and time; writes
    OUT/results.json and OUT/config.yaml.

    \b
    Examples:
      bimfactor bench scanmatch
      bimfactor bench scanmatch --prior runs/prior/duplex
    """
    with _cli_errors(debug):
        cfg = _start(config, overrides, verbose)
        from bimfactor.evaluation.speed import benchmark_scan_matching

        world = _bench_world(prior_dir, cfg)
        with _bench_dir(output, prior_dir):
            prior, model = world or _paper_floor_world(output, cfg)
            result = benchmark_scan_matching(prior, model, cfg, every=every)
            _echo_bench(output, "scanmatch", result, cfg)
