"""Property-based fuzzing (Hypothesis) of every reader of user files: IFC headers, prior folders, sequences and
configs. Whatever the bytes, a reader either reads them or raises one of bimfactor's own errors; through the CLI that
is exit 0 or 2 with one stderr line, never an internal error or a traceback, and no file outside the output folder is
created, changed or removed.

The example counts are bounded and the search is derandomized, so the suite stays fast and repeatable; set
HYPOTHESIS_PROFILE=deep to search longer and with fresh randomness.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from bimfactor.bim.ifc import read_schema
from bimfactor.bim.prior import BimPrior
from bimfactor.cli import app
from bimfactor.config import load_config
from bimfactor.errors import BimfactorError
from bimfactor.io.sequence import read_sequence, write_sequence
from tests.io.synthetic import make_frames, make_meta
from tests.localization.handmade import make_prior

settings.register_profile(
    "suite",
    max_examples=int(os.environ.get("BIMFACTOR_FUZZ_EXAMPLES", "25")),
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
settings.register_profile(
    "deep",
    max_examples=400,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "suite"))

runner = CliRunner()


# ------------------------------------------------------------------------------------------------ helpers


@st.composite
def mutated(draw: st.DrawFn, data: bytes) -> bytes:
    """`data` damaged the ways files get damaged: cut short, bytes flipped, garbage inserted or written over."""
    if not data:
        return draw(st.binary(max_size=64))
    kind = draw(st.sampled_from(["truncate", "flip", "insert", "overwrite", "random"]))
    at = draw(st.integers(0, len(data) - 1))
    if kind == "truncate":
        return data[:at]
    if kind == "flip":
        bit = draw(st.integers(0, 7))
        return data[:at] + bytes([data[at] ^ (1 << bit)]) + data[at + 1 :]
    junk = draw(st.binary(min_size=1, max_size=32))
    if kind == "insert":
        return data[:at] + junk + data[at:]
    if kind == "overwrite":
        return data[:at] + junk + data[at + len(junk) :]
    return draw(st.binary(max_size=256))


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**40), 2**40) | st.floats(allow_nan=True) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=6,
)


@st.composite
def json_edited(draw: st.DrawFn, text: str) -> bytes:
    """A JSON document with one value, at any depth, replaced by another of any type, or one key dropped."""
    doc = json.loads(text)
    node, path = doc, []
    while isinstance(node, dict | list) and node and draw(st.booleans()):
        key = draw(st.sampled_from(sorted(node) if isinstance(node, dict) else range(len(node))))
        path.append(key)
        node = node[key]
    if not path:
        return json.dumps(draw(JSON_VALUES)).encode()
    parent = doc
    for key in path[:-1]:
        parent = parent[key]
    if isinstance(parent, dict) and draw(st.booleans()):
        del parent[path[-1]]
    else:
        parent[path[-1]] = draw(JSON_VALUES)
    return json.dumps(doc).encode()


def snapshot(folder: Path, skip: Path | None = None) -> dict[str, bytes]:
    return {
        str(p.relative_to(folder)): p.read_bytes()
        for p in sorted(folder.rglob("*"))
        if p.is_file() and (skip is None or not p.is_relative_to(skip))
    }


def assert_clean_cli_result(args: list[str], workspace: Path, out: Path) -> int:
    """Run the CLI; exit 0 or 2 with one `error:` line, and nothing in `workspace` but `out` changed."""
    before = snapshot(workspace, skip=out)
    result = runner.invoke(app, args)
    assert isinstance(result.exception, SystemExit | None), f"uncaught {result.exception!r}"
    assert "Traceback" not in result.output
    assert result.exit_code in (0, 2), result.output
    if result.exit_code == 2:
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: ") and "internal" not in lines[0], result.stderr
    assert snapshot(workspace, skip=out) == before
    leftovers = [p.name for p in workspace.iterdir() if ".part" in p.name or p.name.endswith(".old")]
    assert leftovers == []
    return result.exit_code


def fresh(workspace: Path) -> Path:
    """An empty workspace for one example (Hypothesis runs many in one test's tmp_path)."""
    shutil.rmtree(workspace, ignore_errors=True)
    workspace.mkdir(parents=True)
    return workspace


# ------------------------------------------------------------------------------------------------ IFC headers

HEADER = (
    b"ISO-10303-21;\nHEADER;\nFILE_DESCRIPTION(('ViewDefinition [CoordinationView]'),'2;1');\n"
    b"FILE_NAME('x.ifc','2000-01-01T00:00:00',('a'),('b'),'IfcOpenShell','bimfactor','');\n"
    b"FILE_SCHEMA(('IFC4'));\nENDSEC;\n"
)
BODY = b"DATA;\n#1=IFCPROJECT('0pTjeRYDX7tgovKl5oifww',$,'P',$,$,$,$,$,$);\nENDSEC;\nEND-ISO-10303-21;\n"


@given(header=mutated(HEADER))
def test_any_ifc_header_is_read_or_refused(tmp_path: Path, header: bytes) -> None:
    workspace = fresh(tmp_path / "w")
    path = workspace / "model.ifc"
    path.write_bytes(header + BODY)
    with contextlib.suppress(BimfactorError):
        read_schema(path)
    out = workspace / "prior"
    code = assert_clean_cli_result(
        ["prior", str(path), "-o", str(out), "--set", f"bim.ifc.cache_dir={workspace / 'cache'}"], workspace, out
    )
    assert code == 2  # a project with no storey, wall or room is never a prior


# ------------------------------------------------------------------------------------------------ prior folders


@pytest.fixture(scope="module")
def saved_prior(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("fuzz-prior") / "prior"
    make_prior(with_door=True).save(folder)
    return folder


@given(data=st.data(), damaged=st.sampled_from(["prior.json", "arrays.npz"]))
def test_any_damaged_prior_folder_is_read_or_refused(
    tmp_path: Path, saved_prior: Path, data: st.DataObject, damaged: str
) -> None:
    workspace = fresh(tmp_path / "w")
    prior = workspace / "prior"
    shutil.copytree(saved_prior, prior)
    original = (prior / damaged).read_bytes()
    if damaged == "prior.json" and data.draw(st.booleans()):
        (prior / damaged).write_bytes(data.draw(json_edited(original.decode())))
    else:
        (prior / damaged).write_bytes(data.draw(mutated(original)))
    with contextlib.suppress(BimfactorError):
        BimPrior.load(prior)
    assert_clean_cli_result(["prior", str(prior), "--json"], workspace, workspace / "none")


# ------------------------------------------------------------------------------------------------ sequences


@pytest.fixture(scope="module")
def saved_sequence(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("fuzz-sequence") / "seq"
    write_sequence(folder, make_meta(), make_frames(3))
    return folder


@given(data=st.data(), damaged=st.sampled_from(["sequence.json", "frames.csv", "odometry.txt", "depth/000001.png"]))
def test_any_damaged_sequence_is_read_or_refused(
    tmp_path: Path, saved_sequence: Path, data: st.DataObject, damaged: str
) -> None:
    workspace = fresh(tmp_path / "w")
    sequence = workspace / "seq"
    shutil.copytree(saved_sequence, sequence)
    original = (sequence / damaged).read_bytes()
    if damaged == "sequence.json" and data.draw(st.booleans()):
        (sequence / damaged).write_bytes(data.draw(json_edited(original.decode())))
    else:
        (sequence / damaged).write_bytes(data.draw(mutated(original)))
    try:
        for _frame in read_sequence(sequence):
            pass
    except BimfactorError:
        pass
    out = workspace / "out"
    assert_clean_cli_result(["convert", "sequence", str(sequence), "-o", str(out), "--all-frames"], workspace, out)


# ------------------------------------------------------------------------------------------------ configs

KEYS = st.sampled_from(
    ["seed", "smcl", "smcl.num_particles", "smcl.motion.sigma_trans_m", "bim.grid.resolution_m", "nope"]
)
YAML_VALUES = st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats() | st.text(max_size=12)


@st.composite
def config_files(draw: st.DrawFn) -> bytes:
    """A config file as people get them wrong: nested keys with values of any type, or any text or bytes at all."""
    kind = draw(st.sampled_from(["mapping", "text", "bytes"]))
    if kind == "bytes":
        return draw(st.binary(max_size=128))
    if kind == "text":
        return draw(st.text(max_size=128)).encode("utf-8", "surrogatepass")
    lines = []
    for key, value in draw(st.dictionaries(KEYS, YAML_VALUES, max_size=4)).items():
        head, *rest = key.split(".")
        text = json.dumps(value)
        lines.append(f"{head}:" + "".join(f"\n{'  ' * (i + 1)}{part}:" for i, part in enumerate(rest)) + f" {text}")
    return "\n".join(lines).encode()


@given(content=config_files(), override=st.lists(st.text(max_size=24), max_size=2))
def test_any_config_file_and_override_is_loaded_or_refused(tmp_path: Path, content: bytes, override: list[str]) -> None:
    path = tmp_path / "config.yaml"
    path.write_bytes(content)
    for args in ((path, []), (None, override), (path, override)):
        with contextlib.suppress(BimfactorError):
            load_config(*args)


# ------------------------------------------------------------------------------------------------ detections files

DETECTION_LINES = [
    {
        "timestamp": 0.0,
        "detections": [
            {
                "label": "chair",
                "score": 0.9,
                "box": [1, 2, 10, 12],
                "mask": {"size": [24, 32], "counts": [100, 20, 648]},
                "embedding": [1.0, 0.0, 0.0, 0.0],
            }
        ],
    },
    {"frame": 1, "detections": [{"label": "table", "score": 0.5, "box": [0, 0, 32, 24]}]},
]


@given(data=st.data(), how=st.sampled_from(["bytes", "json"]))
def test_any_damaged_detections_file_is_read_or_refused(tmp_path: Path, data: st.DataObject, how: str) -> None:
    """A detector's file damaged byte-wise or with one value of any type anywhere: read, or one InputError line."""
    from bimfactor.perception.detections import read_detections
    from bimfactor.types import CameraIntrinsics

    lines = [json.dumps(line) for line in DETECTION_LINES]
    k = data.draw(st.integers(0, len(lines) - 1))
    if how == "json":
        lines[k] = data.draw(json_edited(lines[k])).decode()
    text = ("\n".join(lines) + "\n").encode()
    if how == "bytes":
        text = data.draw(mutated(text))
    path = tmp_path / "detections.jsonl"
    path.write_bytes(text)
    intrinsics = CameraIntrinsics(32, 24, 30.0, 30.0, 16.0, 12.0)
    try:
        read_detections(path, [0.0, 0.5], [0, 1], intrinsics, embedding_dim=4, encoder="enc")
    except BimfactorError as exc:
        assert "\n" not in str(exc) and str(exc).strip()


# ------------------------------------------------------------------------------------------------ bags


@pytest.fixture(scope="module")
def small_bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    """A two-frame recording as a ROS 1 .bag and as a ROS 2 .mcap file: colour, depth, CameraInfo, tf, odometry."""
    import numpy as np

    from tests.io.bags import R_LINK_OPTICAL, TestBag, rigid

    folder = tmp_path_factory.mktemp("bags")
    out = {}
    for fmt, name in (("ros1", "rec.bag"), ("mcap", "rec-mcap")):
        bag = TestBag(folder / name, fmt)
        bag.camera_info("/cam/info", 10**18, "cam", (8, 6), (8.0, 8.0, 4.0, 3.0))
        bag.tf("/tf_static", 10**18, [("base_link", "cam", rigid((0.0, 0.0, 0.3), R_LINK_OPTICAL))])
        for k in range(2):
            t = 10**18 + k * 10**8
            bag.odometry("/odom", t, np.array([0.1 * k, 0.0, 0.0]))
            bag.image("/cam/color/image_raw", t, np.zeros((6, 8, 3), np.uint8), "rgb8", "cam")
            bag.image("/cam/depth/image_raw", t, np.full((6, 8), 1500, np.uint16), "16UC1", "cam")
        path = bag.write()
        file = path if path.is_file() else next(path.glob("*.mcap"))
        out[file.suffix] = file.read_bytes()
    return out


@settings(max_examples=min(settings.default.max_examples, 15))
@given(data=st.data(), suffix=st.sampled_from([".bag", ".mcap"]))
def test_any_damaged_bag_is_read_or_refused(
    tmp_path: Path, small_bags: dict[str, bytes], data: st.DataObject, suffix: str
) -> None:
    """A ROS 1 bag or an MCAP file damaged the ways files get damaged: read, or one of bimfactor's own errors (found
    this way: a damaged length field made rosbags ask for more memory than exists, and its readers' own errors)."""
    from bimfactor.io.rosbag import read_rosbag

    path = fresh(tmp_path / "w") / f"rec{suffix}"
    path.write_bytes(data.draw(mutated(small_bags[suffix])))
    with contextlib.suppress(BimfactorError):  # the CLI prints it as one line (`_one_line`)
        read_rosbag(path, load_config().io.rosbag)
