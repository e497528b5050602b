"""The `bimfactor` command: parses arguments, calls library functions, prints results, maps errors to exit codes.

Heavy libraries (ifcopenshell, torch, open3d) are imported inside the commands so that `--help` stays fast.
Every error bimfactor raises on purpose becomes one line `error: <message>` on stderr and the error's exit
code (2 for bad input or configuration); anything else is `error: internal: ...` with exit code 1, and
`--debug` (or BIMFACTOR_DEBUG=1) adds the traceback.
"""

from __future__ import annotations

import contextlib
import logging
import sys
import time
import traceback
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import click
import typer

from bimfactor import __version__
from bimfactor.errors import BimfactorError, InputError

if TYPE_CHECKING:
    from bimfactor.bim.prior import BimPrior
    from bimfactor.config import Config

log = logging.getLogger(__name__)

app = typer.Typer(
    name="bimfactor",
    help="Robot localization against a building's BIM model (IFC): CoarseBIMLoc with pose graphs and ICP.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
    rich_markup_mode=None,
    context_settings={"help_option_names": ["-h", "--help"]},
)
bench_app = typer.Typer(
    help="Benchmarks that anyone can rerun; each writes results.json and config.yaml to its output folder.",
    short_help="Benchmarks (results.json + config.yaml per run).",
    no_args_is_help=True,
    rich_markup_mode=None,
)
app.add_typer(bench_app, name="bench")

DEFAULT_DEMO_OUT = Path("runs/demo")
DEFAULT_BENCH_PRIOR_OUT = Path("runs/bench-prior")
DEFAULT_PRIOR_ROOT = Path("runs/prior")

# ------------------------------------------------------------------------------------------ common options

ConfigOption = Annotated[
    str | None,
    typer.Option(
        "--config",
        "-c",
        metavar="PRESET_OR_FILE",
        help="A preset name from configs/ or a YAML file, merged over configs/default.yaml.",
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
VerboseOption = Annotated[bool, typer.Option("--verbose", "-v", help="Log progress (INFO); default is WARNING.")]
DebugOption = Annotated[
    bool,
    typer.Option("--debug", envvar="BIMFACTOR_DEBUG", help="Show the traceback of an error (or BIMFACTOR_DEBUG=1)."),
]


def _one_line(text: str) -> str:
    return " ".join(part.strip() for part in str(text).splitlines() if part.strip()) or "(no message)"


def _fail(message: str, exit_code: int) -> typer.Exit:
    typer.echo(f"error: {_one_line(message)}", err=True)
    return typer.Exit(exit_code)


@contextlib.contextmanager
def _cli_errors(debug: bool) -> Iterator[None]:
    """Turn exceptions into one `error:` line on stderr and an exit code; tracebacks only with --debug."""
    try:
        yield
    except (click.exceptions.Exit, click.ClickException, click.Abort):
        raise
    except BimfactorError as exc:
        if debug:
            traceback.print_exc(file=sys.stderr)
        raise _fail(str(exc), exc.exit_code) from None
    except KeyboardInterrupt:
        raise _fail("interrupted", 130) from None
    except Exception as exc:
        if debug:
            traceback.print_exc(file=sys.stderr)
        raise _fail(f"internal: {type(exc).__name__}: {exc}", 1) from None


_HANDLER_MARK = "_bimfactor_cli"


def _setup_logging(verbose: bool) -> None:
    """Log to the current stderr: bimfactor at INFO with -v, everything else at WARNING."""
    root = logging.getLogger()
    for handler in list(root.handlers):
        if getattr(handler, _HANDLER_MARK, False):
            root.removeHandler(handler)
    handler = logging.StreamHandler(sys.stderr)
    setattr(handler, _HANDLER_MARK, True)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root.addHandler(handler)
    root.setLevel(logging.WARNING)
    logging.getLogger("bimfactor").setLevel(logging.INFO if verbose else logging.WARNING)
    logging.captureWarnings(True)


def _start(config: str | None, overrides: list[str] | None, verbose: bool) -> Config:
    from bimfactor.config import load_config

    _setup_logging(verbose)
    return load_config(config, overrides or [])


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
      bimfactor bench prior
    """


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
        from bimfactor.bim.synth import write_building

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
        from bimfactor.bim.prior import BimPrior, build_prior

        if not model.exists():
            raise InputError(f"no such file or folder: {model}")
        if model.is_dir():
            if output is not None:
                raise InputError(f"{model} is a prior folder; -o applies to IFC input only")
            built, out_dir = BimPrior.load(model), model
        else:
            if model.suffix.lower() != ".ifc":
                raise InputError(f"{model}: expected an .ifc file or a prior folder")
            out_dir = output if output is not None else DEFAULT_PRIOR_ROOT / model.stem
            _check_replaceable(out_dir)
            started = time.perf_counter()
            built = build_prior(model, cfg)
            built.save(out_dir, config_yaml=cfg.dump_yaml())
            log.info("prior built and saved in %.1f s", time.perf_counter() - started)
        summary = _prior_summary(built, out_dir)
        if as_json:
            import json

            typer.echo(json.dumps(summary, indent=2, ensure_ascii=False))
        else:
            typer.echo(_format_prior_summary(built, summary))


def _check_replaceable(out_dir: Path) -> None:
    """Saving replaces the whole folder: refuse a folder that holds anything but a prior."""
    if out_dir.exists() and (
        not out_dir.is_dir() or (any(out_dir.iterdir()) and not (out_dir / "prior.json").is_file())
    ):
        raise InputError(f"{out_dir} exists and is not a prior folder; choose another -o (it would be replaced)")


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


@app.command(short_help="Run the demo: paper-floor building → prior with floor plans.")
def demo(
    output: Annotated[Path, typer.Option("--output", "-o", metavar="OUT", help="Output folder.")] = DEFAULT_DEMO_OUT,
    config: ConfigOption = None,
    overrides: SetOption = None,
    verbose: VerboseOption = False,
    debug: DebugOption = False,
) -> None:
    """Run the end-to-end demo on the procedural "paper-floor" building.

    Steps: synth (OUT/paper-floor.ifc, seed from the config) and prior (OUT/prior/ with floor plans).
    OUT/config.yaml holds the resolved config.

    \b
    Examples:
      bimfactor demo
      bimfactor demo -o runs/demo-seed3 --set seed=3
    """
    with _cli_errors(debug):
        cfg = _start(config, overrides, verbose)
        from bimfactor.demo import STEPS, run_demo

        def report(index: int, step_name: str, seconds: float, message: str) -> None:
            typer.echo(f"[{index + 1}/{len(STEPS)}] {step_name}: {message} ({seconds:.1f} s)")

        result = run_demo(cfg, output, on_step=report)
        typer.echo(f"outputs in {output}/ (resolved config: {output / 'config.yaml'})")
        for figure in result.figures:
            typer.echo(f"  figure: {figure}")


# ------------------------------------------------------------------------------------------ bench


@bench_app.command("prior", short_help="Time cold build, save and reload of the prior on real IFC files.")
def bench_prior(
    ifc: Annotated[
        list[Path] | None,
        typer.Option(
            "--ifc",
            metavar="PATH",
            help="IFC file to benchmark (repeatable; default: AC11-Institute-Var-2-IFC.ifc from ../shared).",
        ),
    ] = None,
    output: Annotated[
        Path, typer.Option("--output", "-o", metavar="OUT", help="Output folder.")
    ] = DEFAULT_BENCH_PRIOR_OUT,
    repeats: Annotated[
        int, typer.Option("--repeats", min=1, metavar="N", help="Timed reloads per prior (median).")
    ] = 5,
    config: ConfigOption = None,
    overrides: SetOption = None,
    verbose: VerboseOption = False,
    debug: DebugOption = False,
) -> None:
    """Time the offline stage: a cold build (empty geometry cache), save, and reload of each prior.

    Writes OUT/results.json, OUT/config.yaml and each prior under OUT/priors/<IFC name>/.
    The text encoder is loaded once before timing; its load time is reported on its own.

    \b
    Examples:
      bimfactor bench prior
      bimfactor bench prior --ifc ../shared/data/ifc/duplex.ifc --ifc ../shared/data/ifc/SampleHouse4.ifc
    """
    with _cli_errors(debug):
        cfg = _start(config, overrides, verbose)
        from bimfactor.evaluation.bench import default_prior_bench_files, format_prior_table, run_prior_bench

        files = list(ifc) if ifc else default_prior_bench_files()
        result = run_prior_bench(files, cfg, output, reload_repeats=repeats)
        typer.echo(format_prior_table(result.rows))
        typer.echo(f"text encoder load (once, not in the builds): {result.embedder_load_s:.1f} s")
        typer.echo(f"results: {output / 'results.json'}")
