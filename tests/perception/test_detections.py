"""The detections backend: the file format (COCO RLE, writer, reader and its checks), box-only segmentation by depth,
and a simulated sequence localized from its detections.jsonl as well as from the sim backend."""

from __future__ import annotations

import copy
import csv
import json
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from bimfactor.config import Config, load_config, updated
from bimfactor.errors import InputError
from bimfactor.evaluation.graph import GraphEvalParams, evaluate_graph, observed_objects
from bimfactor.io.sequence import Sequence, read_sequence
from bimfactor.perception.boxes import box_mask
from bimfactor.perception.detections import (
    DETECTIONS_FILE,
    DetectionRecord,
    FrameRecord,
    attach_detections,
    read_detections,
    rle_decode,
    rle_encode,
    rle_runs,
    write_detections,
)
from bimfactor.perception.pipeline import choose_backend, make_perception
from bimfactor.sim.simulate import SimResult
from bimfactor.types import CameraIntrinsics, SequenceMeta
from tests.cli import assert_one_line_error, invoke

# ------------------------------------------------------------------------------------------ COCO RLE


def _reference_mask() -> np.ndarray:
    """A 20 x 15 mask with long runs, runs shorter than the one two before (negative deltas) and a lone corner."""
    mask = np.zeros((20, 15), bool)
    mask[3:17, 2:12] = True
    for i in range(15):
        mask[(i * 7) % 20, i] = not mask[(i * 7) % 20, i]
    mask[19, 14] = True
    return mask


# What pycocotools 2.0.11 `mask.encode` gives for these masks (computed once with it; it is not a dependency).
REFERENCE_COMPRESSED = "01j00E:BG3OM=5GK354KE4>1GK15620NJKO590Bd0001"
REFERENCE_RUNS = [0, 1, 26, 1, 15, 11, 1, 2, 4, 1, 1, 14, 6, 5, 1, 8, 6, 12, 1, 1, 5, 15, 6, 6, 1, 7, 6, 13, 8, 13, 6]
REFERENCE_RUNS += [7, 1, 6, 6, 15, 6, 1, 26, 1, 26, 2]
SMALL_COMPRESSED = "01>3E0000000<M"  # 7 x 9: rows 1-4, columns 2-6, and the two corners (0, 0), (6, 8)
BIG_BOX_COMPRESSED = "Tag0\\9d5" + "0" * 1097 + "ldb0"  # 480 x 640: rows 100-399, columns 50-599


def test_rle_decodes_compressed_and_uncompressed_counts_as_pycocotools_writes_them() -> None:
    expected = _reference_mask()
    assert np.array_equal(rle_decode({"size": [20, 15], "counts": REFERENCE_COMPRESSED}), expected)
    assert np.array_equal(rle_decode({"size": [20, 15], "counts": REFERENCE_RUNS}), expected)
    assert rle_runs(REFERENCE_COMPRESSED).tolist() == REFERENCE_RUNS
    assert rle_runs(REFERENCE_COMPRESSED.encode()).tolist() == REFERENCE_RUNS  # bytes, as pycocotools returns
    small = np.zeros((7, 9), bool)
    small[1:5, 2:7] = small[0, 0] = small[6, 8] = True
    assert np.array_equal(rle_decode({"size": [7, 9], "counts": SMALL_COMPRESSED}), small)
    big = np.zeros((480, 640), bool)
    big[100:400, 50:600] = True
    assert np.array_equal(rle_decode({"size": [480, 640], "counts": BIG_BOX_COMPRESSED}), big)


def test_rle_encode_writes_what_pycocotools_writes_and_round_trips() -> None:
    assert rle_encode(_reference_mask()) == {"size": [20, 15], "counts": REFERENCE_COMPRESSED}
    big = np.zeros((480, 640), bool)
    big[100:400, 50:600] = True
    assert rle_encode(big)["counts"] == BIG_BOX_COMPRESSED
    rng = np.random.default_rng(5)
    for shape in [(1, 1), (3, 1), (31, 17), (120, 160)]:
        for density in (0.0, 0.05, 0.5, 1.0):
            mask = rng.random(shape) < density
            assert np.array_equal(rle_decode(rle_encode(mask)), mask), (shape, density)


@pytest.mark.parametrize(
    ("counts", "message"),
    [("01j00E:BG3OM=5GK354KE4>1GK15620NJKO590Bd00", "pixels"), ("0a", "middle of a value"), ("0~", "not in")],
)
def test_rle_refuses_counts_that_do_not_decode(counts: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        rle_decode({"size": [20, 15], "counts": counts})


# ------------------------------------------------------------------------------------------ writer and reader

K = CameraIntrinsics(32, 24, 30.0, 30.0, 15.5, 11.5)
TIMES = np.array([0.0, 0.5, 1.0, 1.5])
INDICES = np.array([0, 1, 2, 3])


def _records() -> list[FrameRecord]:
    mask = np.zeros((24, 32), bool)
    mask[4:10, 6:12] = True
    rle_list = {"size": [24, 32], "counts": rle_runs(rle_encode(mask)["counts"]).tolist()}
    embedding = np.arange(1.0, 9.0)
    return [
        FrameRecord([DetectionRecord("chair", 0.83, [6.0, 4.0, 12.0, 10.0], mask, embedding)], timestamp_s=0.0004),
        FrameRecord([], timestamp_s=0.5),
        FrameRecord(
            [
                DetectionRecord("table", 0.5, np.array([0.0, 0.0, 32.0, 24.0])),
                DetectionRecord("sofa", 1.0, [-0.5, 2.0, 10.0, 24.6], rle_list),
            ],
            index=3,
        ),
    ]


def test_written_detections_read_back(tmp_path: Path) -> None:
    path = tmp_path / DETECTIONS_FILE
    assert write_detections(path, _records()) == 3
    lines = [json.loads(line) for line in path.read_text().splitlines()]
    assert lines[0]["timestamp"] == 0.0004 and lines[2]["frame"] == 3 and lines[1]["detections"] == []
    assert set(lines[0]["detections"][0]) == {"label", "score", "box", "mask", "embedding"}
    assert set(lines[2]["detections"][0]) == {"label", "score", "box"}  # mask and embedding are optional

    table = read_detections(path, TIMES, INDICES, K, embedding_dim=8)
    (chair,) = table.at(0.0)  # matched within a millisecond
    assert chair.label == "chair" and chair.box_score == chair.text_score == 0.83
    assert np.array_equal(chair.box_xyxy, [6, 4, 12, 10])
    decoded = rle_decode({"size": [24, 32], "counts": chair.mask_runs.tolist()})
    assert decoded.sum() == 36 and decoded[4:10, 6:12].all()
    assert chair.embedding is not None
    np.testing.assert_allclose(chair.embedding, np.arange(1.0, 9.0) / np.linalg.norm(np.arange(1.0, 9.0)), atol=1e-5)
    assert table.at(0.5) == [] and table.at(1.0) == []  # an empty list, and a frame the file does not mention
    table_det, sofa = table.at(1.5)
    assert table_det.mask_runs is None and table_det.embedding is None
    assert np.array_equal(sofa.box_xyxy, [0.0, 2.0, 10.0, 24.0])  # within a pixel of the border: clipped
    assert sofa.mask_runs is not None and sofa.mask_runs.sum() == 24 * 32
    assert table.n_detections == 3 and table.summary().startswith("3 detections in 3 frames, 2 with a mask")


def test_the_writer_refuses_what_the_reader_would(tmp_path: Path) -> None:
    path = tmp_path / DETECTIONS_FILE
    chair = DetectionRecord("chair", 0.5, [1, 2, 3, 4])
    with pytest.raises(InputError, match="record 1 names no frame"):
        write_detections(path, [FrameRecord([chair], 0.0), FrameRecord([chair])])
    with pytest.raises(InputError, match=r"record 0, detection 0: box \[1.0, 2.0, nan, 4.0\] is not finite"):
        write_detections(path, [FrameRecord([DetectionRecord("chair", 0.5, [1, 2, np.nan, 4])], 0.0)])
    wide, narrow = (DetectionRecord("chair", 0.5, [1, 2, 3, 4], embedding=np.ones(n)) for n in (4, 3))
    with pytest.raises(InputError, match=r"record 1, detection 0: embedding has 3 values, .*record 0 has 4"):
        write_detections(path, [FrameRecord([wide], 0.0), FrameRecord([narrow], 0.5)])
    assert not path.exists()  # nothing half written


def _line(**detection) -> dict:
    return {"timestamp": 0.5, "detections": [{"label": "chair", "score": 0.5, "box": [1, 2, 10, 12], **detection}]}


BAD_LINES = [
    ("not json {", "line 2: not JSON"),
    ("[1, 2]", "line 2: a line must be a JSON object"),
    ({"detections": []}, "line 2: missing key 'timestamp'"),
    ({"timestamp": 0.5}, "line 2: missing key 'detections'"),
    ({"timestamp": 0.5, "detections": [{"label": "chair", "box": [1, 2, 3, 4]}]}, "missing key 'score'"),
    ({"timestamp": 7.25, "detections": []}, "line 2: timestamp 7.25 matches no frame within 1 ms"),
    ({"frame": 9, "detections": []}, "line 2: frame 9 is not in the sequence"),
    ({"frame": -1, "detections": []}, "frame -1 is not a frame index"),
    ({"timestamp": 0.0, "detections": []}, "line 2: frame at 0.0 s was given already on line 1"),
    ({"timestamp": 0.5, "frame": 2, "detections": []}, "name two different frames"),
    (_line(box=[1, 2, float("nan"), 12]), "line 2, detection 0: box [1, 2, nan, 12] is not finite"),
    (_line(box=[1, 2, float("inf"), 12]), "is not finite"),
    (_line(box=[10, 2, 1, 12]), "line 2, detection 0: box [10, 2, 1, 12] is inverted or empty"),
    (_line(box=[1, 2, 40, 12]), "line 2, detection 0: box [1, 2, 40, 12] lies outside the 32x24 image"),
    (_line(box=[1, 2, 3]), "is not [x0, y0, x1, y1]"),
    (_line(score=1.2), "line 2, detection 0: score 1.2 is not a number in [0, 1]"),
    (_line(score=-0.1), "score -0.1 is not a number in [0, 1]"),
    (_line(label=""), "label '' is not a non-empty text"),
    (
        _line(mask={"size": [48, 64], "counts": [3072]}),
        "mask size [48, 64] (height, width) is not the image's [24, 32]",
    ),
    (_line(mask={"size": [24, 32], "counts": [700]}), "mask counts cover 700 pixels"),
    (_line(mask={"size": [24, 32], "counts": "0a"}), "mask does not decode"),
    (_line(mask=[1, 2]), "mask must be COCO RLE"),
    (_line(mask={"size": [24, 32], "counts": [2**70, 1]}), "a run is longer than any image"),  # was OverflowError
    (_line(mask={"size": [24, 32], "counts": [2**39, 2**39]}), "mask counts hold a run of 549755813888 pixels"),
    (
        {"timestamp": 0.5, "detections": _line()["detections"] * 1001},
        "line 2: 1001 detections in one frame, more than 1000",
    ),
    (_line(embedding=[0.1] * 5), "line 2, detection 0: embedding has 5 values, the prior's text encoder (enc) gives 8"),
    (_line(embedding=[0.0] * 8), "embedding is all zeros"),
]


@pytest.mark.parametrize(("line", "message"), BAD_LINES, ids=[m for _, m in BAD_LINES])
def test_each_bad_line_is_one_input_error_naming_it(tmp_path: Path, line, message: str) -> None:
    path = tmp_path / "d.jsonl"
    text = line if isinstance(line, str) else json.dumps(line)
    path.write_text(json.dumps({"timestamp": 0.0, "detections": []}) + "\n" + text + "\n")
    with pytest.raises(InputError) as caught:
        read_detections(path, TIMES, INDICES, K, embedding_dim=8, encoder="enc")
    assert str(caught.value).startswith(f"{path} line 2")
    assert message in str(caught.value) and "\n" not in str(caught.value)


def test_embeddings_of_one_file_must_share_a_width_when_no_prior_says_it(tmp_path: Path) -> None:
    path = tmp_path / "d.jsonl"
    second = {"frame": 2, "detections": _line(embedding=[1, 0])["detections"]}
    path.write_text(json.dumps(_line(embedding=[0.1] * 4)) + "\n" + json.dumps(second) + "\n")
    with pytest.raises(InputError, match=r"line 2, detection 0: embedding has 2 values, .* line 1 has 4"):
        read_detections(path, TIMES, INDICES, K)


@pytest.mark.parametrize("scale", [1e308, 1e-300])
def test_an_embedding_of_huge_or_tiny_values_keeps_its_direction(tmp_path: Path, scale: float) -> None:
    """Values near float64's limits: normalised without overflow or underflow (no warning), the direction kept."""
    path = tmp_path / "d.jsonl"
    path.write_text(json.dumps(_line(embedding=[scale, scale, 0.0, 0.0])) + "\n")
    with np.errstate(all="raise"):
        table = read_detections(path, TIMES, INDICES, K, embedding_dim=4, encoder="enc")
    (detection,) = table.detections[0]
    np.testing.assert_allclose(detection.embedding, [2**-0.5, 2**-0.5, 0.0, 0.0], rtol=1e-6)


def test_attach_copies_a_checked_file_into_a_sequence_and_can_drop_unkept_frames(
    meeting_orbit: SimResult, tmp_path: Path
) -> None:
    from bimfactor.io.sequence import write_sequence

    folder = tmp_path / "seq"
    write_sequence(folder, meeting_orbit.meta, meeting_orbit.frames[:3])
    times = [f.timestamp_s for f in meeting_orbit.frames[:4]]
    source = tmp_path / "all-frames.jsonl"
    write_detections(source, [FrameRecord([DetectionRecord("chair", 0.9, [1, 1, 9, 9])], t) for t in times])
    with pytest.raises(InputError, match=r"line 4: timestamp .* matches no frame"):
        attach_detections(folder, source)
    assert not (folder / DETECTIONS_FILE).exists()
    table = attach_detections(folder, source, unknown_frames="drop")
    assert table.lines == [1, 2, 3] and table.dropped_lines == [4]
    assert (folder / DETECTIONS_FILE).read_text().splitlines() == source.read_text().splitlines()[:3]
    sequence = read_sequence(folder)
    again = read_detections(
        folder / DETECTIONS_FILE, sequence.timestamps(), sequence.indices(), sequence.meta.intrinsics
    )
    assert again.n_detections == 3


# ------------------------------------------------------------------------------------------ choosing the backend


def test_auto_picks_sim_then_detections_then_the_shipped_detector(test_config: Config) -> None:
    p = test_config.perception
    simulated = SequenceMeta("sim", "sim", K, np.eye(4), instances=[{"id": 0, "object_id": 0, "label": "chair"}])
    real = SequenceMeta("bag", "rosbag", K, np.eye(4))
    assert p.backend == "auto"
    assert choose_backend(p, simulated, has_detections=True) == "sim"
    assert choose_backend(p, real, has_detections=True) == "detections"
    assert choose_backend(p, real, has_detections=False) == "yolox"  # never an error for lack of weights
    assert choose_backend(updated(p, {"vlm.yolo_world_weights": "yw.pt"}), real, has_detections=False) == "yolox"
    assert choose_backend(updated(p, {"backend": "vlm"}), real, has_detections=False) == "vlm"
    assert choose_backend(updated(p, {"backend": "detections"}), simulated, has_detections=True) == "detections"
    with pytest.raises(InputError, match=r"perception\.backend=detections needs a detections file"):
        choose_backend(updated(p, {"backend": "detections"}), simulated, has_detections=False)


# ------------------------------------------------------------------------------------------ box-only detections


def test_box_only_detections_become_nodes_by_depth_clustering(
    test_config: Config, text_embedder, paper_floor, meeting_orbit: SimResult, tmp_path: Path
) -> None:
    """The clean sim detector's boxes alone, with true poses. Measured: box masks against the true instance IoU
    median 0.66 (69 % above 0.5); 52 of 54 detections lifted, 10 nodes for the 6 objects, precision 0.60, recall 1.0
    (with the sim segmenter's masks: 7 nodes, 0.86 / 1.0)."""
    perfect = copy.deepcopy(meeting_orbit)
    for frame in perfect.frames:
        frame.odom_pose = frame.gt_pose.copy()
    sim = make_perception(test_config, perfect.meta, text_embedder, sim_preset="clean")
    records, ious = [], []
    for frame in perfect.frames:
        detections, _, _ = sim.perceive(frame)
        records.append(
            FrameRecord([DetectionRecord(d.label, d.box_score, d.box_xyxy) for d in detections], frame.timestamp_s)
        )
        for d in detections:
            if d.gt_instance_id is not None and d.gt_instance_id >= 0:
                meta, p = perfect.meta, test_config.perception
                mask = box_mask(frame.depth_m, d.box_xyxy, meta.intrinsics, meta.T_base_camera, p, 0.15)
                truth = frame.instance_ids == d.gt_instance_id
                ious.append((mask & truth).sum() / (mask | truth).sum())
    assert len(ious) >= 30 and np.median(ious) >= 0.6

    path = tmp_path / DETECTIONS_FILE
    write_detections(path, records)
    sequence = Sequence.from_frames(perfect.meta, perfect.frames)
    table = read_detections(path, sequence.timestamps(), sequence.indices(), perfect.meta.intrinsics, text_embedder.dim)
    cfg = updated(test_config, {"perception.backend": "detections"})
    perception = make_perception(cfg, perfect.meta, text_embedder, detections=table)
    assert perception.backend == "detections"
    results = perception.run(perfect.frames)
    assert sum(r.stats.n_lifted for r in results) >= 0.8 * table.n_detections
    labels = {perception.graph.nodes[k].label for k in perception.graph.nodes}
    assert {"chair", "table"} <= labels
    gt = np.stack([f.gt_pose for f in perfect.frames])
    seen = sorted(
        i for i in observed_objects(perfect.frames, perfect.meta) if paper_floor.prior.objects[i].label != "door"
    )
    report = evaluate_graph(perception.graph, paper_floor.prior, 0, gt, gt, seen, GraphEvalParams())
    assert report["n_objects"] == 6 and report["recall"] >= 0.8 and report["precision"] >= 0.5


# ------------------------------------------------------------------------------------------ end to end through the CLI


@pytest.fixture(scope="module")
def simulated(paper_floor_prior: Path, tmp_path_factory: pytest.TempPathFactory, cli_config_args: list[str]) -> Path:
    """Trajectory 0 of the paper floor, 20 keyframes, simulated through the CLI (with its detections.jsonl)."""
    folder = tmp_path_factory.mktemp("detections") / "seq"
    length = "evaluation.trajectory_length=20"
    result = invoke("simulate", paper_floor_prior, "-o", folder, "--set", length, *cli_config_args)
    assert result.exit_code == 0, result.output
    return folder


LOCALIZE = ("--set", "smcl.num_particles=300", "--set", "smcl.resampler.max_particles=3000")


def _localize(prior: Path, sequence: Path, run: Path, *args: str) -> tuple[str, np.ndarray]:
    """`localize` into `run`: its first output line and (T,) the translation error of each step (m)."""
    result = invoke("localize", prior, sequence, "-o", run, *LOCALIZE, *args)
    assert result.exit_code == 0, result.output
    steps = list(csv.DictReader((run / "steps.csv").read_text().splitlines()))
    errors = [math.hypot(float(r["x"]) - float(r["gt_x"]), float(r["y"]) - float(r["gt_y"])) for r in steps]
    return result.stdout.splitlines()[0], np.asarray(errors)


def test_simulate_writes_the_sim_detectors_detections(simulated: Path, test_config: Config) -> None:
    sequence = read_sequence(simulated)
    table = read_detections(
        simulated / DETECTIONS_FILE, sequence.timestamps(), sequence.indices(), sequence.meta.intrinsics, 384
    )
    assert len(table.lines) == len(sequence) == 20  # one line per frame, an empty list where nothing was detected
    assert table.n_detections >= 20
    every = [d for ds in table.detections for d in ds]
    assert all(d.mask_runs is not None and d.embedding is not None for d in every)
    assert min(d.box_score for d in every) >= test_config.perception.box_threshold


@pytest.fixture(scope="module")
def sim_run(
    paper_floor_prior: Path, simulated: Path, tmp_path_factory: pytest.TempPathFactory
) -> tuple[str, np.ndarray]:
    return _localize(paper_floor_prior, simulated, tmp_path_factory.mktemp("sim-run") / "run")


def test_a_simulated_sequence_localizes_with_the_sim_backend_by_default(sim_run: tuple[str, np.ndarray]) -> None:
    first, errors = sim_run
    assert first == "perception: sim (the simulator's instance buffer, error preset yolox)"
    assert errors[-1] < 1.0


def test_its_detections_file_localizes_exactly_as_the_sim_backend(
    paper_floor_prior: Path, simulated: Path, sim_run: tuple[str, np.ndarray], tmp_path: Path
) -> None:
    """simulate writes the sim backend's detections of the stored frames with the run's seed (masks exact, embeddings
    as float32), so the detections backend gives the very same run. Measured (20 keyframes, 300 particles): final
    translation error 0.25 m, median over the second half 0.17 m, for both."""
    first, errors = _localize(paper_floor_prior, simulated, tmp_path / "run", "--set", "perception.backend=detections")
    counts = r": (\d+) detections in 20 frames, \1 with a mask, \1 with an embedding"
    assert re.fullmatch(re.escape(f"perception: detections from {simulated / DETECTIONS_FILE}") + counts, first), first
    assert load_config(tmp_path / "run" / "config.yaml").perception.backend == "detections"
    _, sim_errors = sim_run
    assert errors[-1] < 1.0
    np.testing.assert_array_equal(errors, sim_errors)


def test_a_sequence_without_instances_picks_its_detections_even_box_and_label_only(
    paper_floor_prior: Path, simulated: Path, tmp_path: Path
) -> None:
    """As a converted recording with a detector's boxes and labels only: no instance table, no masks, no embeddings.
    Measured (20 keyframes, 300 particles): final translation error 0.28 m, median over the second half 0.17 m."""
    real = tmp_path / "real"
    shutil.copytree(simulated, real)
    meta = json.loads((real / "sequence.json").read_text())
    meta["instances"] = []
    (real / "sequence.json").write_text(json.dumps(meta))
    lines = [json.loads(line) for line in (real / DETECTIONS_FILE).read_text().splitlines()]
    for line in lines:
        for d in line["detections"]:
            del d["mask"], d["embedding"]
    (real / DETECTIONS_FILE).write_text("".join(json.dumps(line) + "\n" for line in lines))
    first, errors = _localize(paper_floor_prior, real, tmp_path / "run")
    assert first.startswith(f"perception: detections from {real / DETECTIONS_FILE}: ")
    assert first.endswith(", 0 with a mask, 0 with an embedding")
    assert errors[-1] < 1.0


def test_a_converted_recording_without_detections_localizes_through_the_shipped_detector(
    paper_floor_prior: Path, simulated: Path, tmp_path: Path
) -> None:
    """No instance table and no detections file, as a recording converted from a bag without a detector topic:
    `auto` runs YOLOX-Nano on the colour frames (the run's config records it) and the run completes."""
    real = tmp_path / "real"
    shutil.copytree(simulated, real)
    meta = json.loads((real / "sequence.json").read_text())
    meta["instances"] = []
    (real / "sequence.json").write_text(json.dumps(meta))
    (real / DETECTIONS_FILE).unlink()
    converted = tmp_path / "converted"
    result = invoke("convert", "sequence", real, "-o", converted, "--all-frames")
    assert result.exit_code == 0, result.output
    first, errors = _localize(paper_floor_prior, converted, tmp_path / "run")
    assert first.startswith("perception: yolox"), first
    assert load_config(tmp_path / "run" / "config.yaml").perception.backend == "yolox"
    assert len(errors) == 20 and np.all(np.isfinite(errors))


def _frame0(**detection) -> dict:
    return {"frame": 0, "detections": [{"label": "chair", "score": 1.0, "box": [5, 5, 9, 9], **detection}]}


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("{oops", "line 1: not JSON"),
        ({"detections": []}, "line 1: missing key 'timestamp'"),
        ({"timestamp": 1e6, "detections": []}, "line 1: timestamp 1000000.0 matches no frame"),
        ({"frame": 20, "detections": []}, "line 1: frame 20 is not in the sequence"),
        ({"frame": 0, "detections": [{"label": "chair", "score": 0.5, "box": [5, 5, 1, 9]}]}, "is inverted or empty"),
        ({"frame": 0, "detections": [{"label": "chair", "score": 0.5, "box": [5, 5, 9, 999]}]}, "outside the 320x240"),
        ({"frame": 0, "detections": [{"label": "chair", "score": 2, "box": [5, 5, 9, 9]}]}, "score 2 is not"),
        (
            _frame0(embedding=[0.5] * 512),
            "line 1, detection 0: embedding has 512 values, the prior's text encoder (all-MiniLM-L6-v2) gives 384",
        ),
        (
            _frame0(mask={"size": [480, 640], "counts": [307200]}),
            "mask size [480, 640] (height, width) is not the image's [240, 320]",
        ),
    ],
)
def test_localize_refuses_a_bad_detections_file_in_one_line(
    paper_floor_prior: Path, simulated: Path, tmp_path: Path, line, message: str
) -> None:
    bad = tmp_path / "bad.jsonl"
    bad.write_text((line if isinstance(line, str) else json.dumps(line)) + "\n")
    result = invoke("localize", paper_floor_prior, simulated, "-o", tmp_path / "run", "--detections", bad)
    assert assert_one_line_error(result, contains=message).startswith(f"error: {bad} line 1")
    assert result.stdout == "" and not (tmp_path / "run").exists()


def test_localize_detections_option_needs_a_file_and_a_backend_that_reads_it(
    paper_floor_prior: Path, simulated: Path, tmp_path: Path
) -> None:
    run = tmp_path / "run"
    nothing = invoke("localize", paper_floor_prior, simulated, "-o", run, "--detections", tmp_path / "none.jsonl")
    assert_one_line_error(nothing, contains="no such detections file")
    given = simulated / DETECTIONS_FILE
    sim = invoke(
        "localize", paper_floor_prior, simulated, "-o", run, "--detections", given, "--set", "perception.backend=sim"
    )
    assert_one_line_error(sim, contains="--detections reads a detector's detections, but perception.backend is sim")


def test_convert_keeps_the_detections_of_the_frames_it_keeps(simulated: Path, tmp_path: Path) -> None:
    """`convert sequence` carries a sequence's detections.jsonl over to the keyframes it keeps; `--detections FILE`
    stores a given file instead; a line for a frame the recording does not have is refused before anything is
    written."""
    kept = tmp_path / "every-metre"
    result = invoke("convert", "sequence", simulated, "-o", kept, "--set", "localization.keyframe_distance_m=1.0")
    assert result.exit_code == 0, result.output
    assert "detections: " in result.stdout and f"from {simulated / DETECTIONS_FILE}" in result.stdout
    source = [json.loads(line) for line in (simulated / DETECTIONS_FILE).read_text().splitlines()]
    stored = [json.loads(line) for line in (kept / DETECTIONS_FILE).read_text().splitlines()]
    times = {float(t) for t in read_sequence(kept).timestamps()}
    assert 0 < len(stored) < len(source)
    assert stored == [line for line in source if line["timestamp"] in times]

    given = tmp_path / "given.jsonl"
    given.write_text(json.dumps(source[3]) + "\n")
    one = tmp_path / "one"
    result = invoke("convert", "sequence", simulated, "-o", one, "--all-frames", "--detections", given)
    assert result.exit_code == 0, result.output
    assert (one / DETECTIONS_FILE).read_text().splitlines() == [json.dumps(source[3])]

    stray = tmp_path / "stray.jsonl"
    stray.write_text(json.dumps({"timestamp": 12345.0, "detections": []}) + "\n")
    result = invoke("convert", "sequence", simulated, "-o", tmp_path / "none", "--detections", stray)
    assert_one_line_error(result, contains=f"{stray} line 1")
    assert not (tmp_path / "none").exists()
