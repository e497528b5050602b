"""The `detections` perception backend: per-frame detections that any external detector wrote to a file.

The file (JSON Lines, one line per colour frame, each naming its frame by `timestamp` or `frame` index, with labelled,
scored boxes and optional RLE masks and embeddings) is specified in docs/perception.md. `read_detections` checks the
whole file before any heavy work, each problem one `InputError` naming the file and line; `write_detections` writes
it; `attach_detections` checks a file against a sequence folder and copies it in.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from bimfactor.errors import InputError
from bimfactor.io.atomic import write_text_atomic
from bimfactor.perception.base import Detection, passes_thresholds
from bimfactor.types import CameraIntrinsics, Frame

log = logging.getLogger(__name__)

DETECTIONS_FILE = "detections.jsonl"
"""The detections file's name in a sequence folder."""
TIMESTAMP_TOLERANCE_S = 1e-3
"""A line's timestamp names the frame whose `timestamp_s` is within this (a 30 Hz camera's frames are 33 ms apart)."""
BOX_SLACK_PX = 1.0
"""A box may pass the image border by this much (then it is clipped); farther out it is refused."""
UNIT_TOLERANCE = 1e-6
"""An embedding whose norm is this close to 1 is kept as written (float32 rounding); any other is normalised."""
MAX_DETECTIONS = 1000
"""A line with more detections than this is refused before any is parsed: ten times what COCO detectors keep (100,
300 at most), and each costs a mask of the image in the front end."""
MAX_RUN = 2**40
"""No mask has a run longer than this (a 1-megapixel image has 2^20 pixels); longer is a broken file, refused before
the runs are summed."""


# ------------------------------------------------------------------------------------------ COCO run-length encoding


def rle_runs(counts: str | bytes | Sequence[int]) -> np.ndarray:
    """(R,) int64 run lengths of COCO RLE `counts`: pycocotools' compressed string or the uncompressed list.

    The string packs each run (after the third, as the difference to the run two before it) into 5-bit groups, least
    significant first, one character (48 + group) each; bit 0x20 says another group follows, bit 0x10 of the last
    group is the sign. ValueError for text that is not such a string, or negative runs.
    """
    if isinstance(counts, bytes):
        counts = counts.decode("ascii", errors="replace")
    if isinstance(counts, str):
        runs = _runs_from_string(counts)
    else:
        if any(isinstance(c, bool) or not isinstance(c, int | np.integer) for c in counts):
            raise ValueError("uncompressed counts must be whole numbers")
        if any(abs(int(c)) > MAX_RUN for c in counts):
            raise ValueError(f"a run is longer than any image ({MAX_RUN} pixels)")
        runs = np.asarray(list(counts), np.int64)
    if np.any(runs < 0):
        raise ValueError("counts decode to a negative run")
    return runs


def _runs_from_string(text: str) -> np.ndarray:
    if not text:
        return np.zeros(0, np.int64)
    if not text.isascii():
        raise ValueError("compressed counts must be ASCII")
    c = np.frombuffer(text.encode("ascii"), np.uint8).astype(np.int64) - 48
    if np.any((c < 0) | (c > 63)):
        raise ValueError(f"character {text[int(np.flatnonzero((c < 0) | (c > 63))[0])]!r} is not in compressed counts")
    ends = np.flatnonzero((c & 0x20) == 0)  # the last group of each value
    if len(ends) == 0 or ends[-1] != len(c) - 1:
        raise ValueError("compressed counts end in the middle of a value")
    starts = np.concatenate([[0], ends[:-1] + 1])
    lengths = ends - starts + 1
    if lengths.max() > 12:
        raise ValueError("compressed counts hold a value beyond 60 bits")
    position = np.arange(len(c)) - np.repeat(starts, lengths)
    values = np.add.reduceat((c & 0x1F) << (5 * position), starts)
    negative = (c[ends] & 0x10) != 0
    values[negative] -= np.left_shift(np.int64(1), 5 * lengths[negative])  # sign extension of the top group
    runs = values.copy()
    runs[1::2] = np.cumsum(values[1::2])  # run i (> 2) is stored as its difference to run i − 2
    runs[2::2] = np.cumsum(values[2::2])
    return runs


def _runs_to_string(runs: np.ndarray) -> str:
    out = []
    for i, run in enumerate(runs):
        x = int(run) - (int(runs[i - 2]) if i > 2 else 0)
        more = True
        while more:
            group = x & 0x1F
            x >>= 5
            more = x != -1 if group & 0x10 else x != 0
            out.append(chr(48 + (group | (0x20 if more else 0))))
    return "".join(out)


def rle_decode(rle: Mapping[str, Any]) -> np.ndarray:
    """(h, w) bool mask of a COCO RLE `{"size": [h, w], "counts": ...}`; ValueError when it does not decode."""
    height, width = (int(v) for v in rle["size"])
    return runs_to_mask(rle_runs(rle["counts"]), height, width)


def runs_to_mask(runs: np.ndarray, height: int, width: int) -> np.ndarray:
    """(height, width) bool mask of (R,) column-major run lengths, zeros first; ValueError unless they fill it."""
    if int(np.sum(runs)) != height * width:
        raise ValueError(f"counts cover {int(np.sum(runs))} pixels, a {height}x{width} mask has {height * width}")
    values = np.zeros(len(runs), bool)
    values[1::2] = True
    return np.repeat(values, runs).reshape(width, height).T


def rle_encode(mask: np.ndarray) -> dict[str, Any]:
    """COCO RLE of an (h, w) bool mask, counts as pycocotools' compressed string: `{"size": [h, w], "counts": str}`."""
    mask = np.asarray(mask, bool)
    height, width = mask.shape
    flat = mask.T.ravel()  # column-major, as COCO counts
    changes = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    runs = np.diff(np.concatenate([[0], changes, [flat.size]]))
    if flat.size and flat[0]:
        runs = np.concatenate([[0], runs])
    return {"size": [height, width], "counts": _runs_to_string(runs)}


# ------------------------------------------------------------------------------------------ records and the writer


@dataclass
class DetectionRecord:
    """One detection as a detector reports it: what one entry of a detections file holds.

    `box_xyxy` (4,) pixels x0, y0, x1, y1 (x1 / y1 exclusive); `mask` (H, W) bool or a COCO RLE dict; `embedding`
    (D,) in the prior's embedding space.
    """

    label: str
    score: float
    box_xyxy: Sequence[float] | np.ndarray
    mask: np.ndarray | Mapping[str, Any] | None = None
    embedding: Sequence[float] | np.ndarray | None = None


@dataclass
class FrameRecord:
    """The detections of one colour frame, named by its stamp `timestamp_s` or its frame `index` (one of the two)."""

    detections: list[DetectionRecord]
    timestamp_s: float | None = None
    index: int | None = None


def record_json(record: FrameRecord) -> dict[str, Any]:
    """The JSON object of one line of a detections file."""
    line: dict[str, Any] = {}
    if record.timestamp_s is not None:
        line["timestamp"] = float(record.timestamp_s)
    if record.index is not None:
        line["frame"] = int(record.index)
    entries = []
    for d in record.detections:
        entry: dict[str, Any] = {
            "label": str(d.label),
            "score": float(d.score),
            "box": [float(v) for v in np.asarray(d.box_xyxy, float).reshape(-1)],
        }
        if d.mask is not None:
            rle = dict(d.mask) if isinstance(d.mask, Mapping) else rle_encode(d.mask)
            if isinstance(rle["counts"], bytes):
                rle["counts"] = rle["counts"].decode("ascii")
            entry["mask"] = {"size": [int(v) for v in rle["size"]], "counts": rle["counts"]}
        if d.embedding is not None:
            entry["embedding"] = _float32_texts(d.embedding)
        entries.append(entry)
    line["detections"] = entries
    return line


def _float32_texts(values: Sequence[float] | np.ndarray) -> list[float]:
    """Values as float32, each as the shortest decimal that reads back to the same float32 (7–9 digits, not 17)."""
    return [float(np.format_float_positional(v, unique=True)) for v in np.asarray(values, np.float32).reshape(-1)]


def write_detections(path: str | Path, records: Iterable[FrameRecord]) -> int:
    """Write a detections file (the module's format) atomically; returns the number of lines.

    Each record is checked as the reader checks a line (bar what needs the sequence: the frame, the image size):
    InputError naming the record.
    """
    lines, checks = [], _Checks()  # one for the file: every embedding has the first one's width
    for k, record in enumerate(records):
        if record.timestamp_s is None and record.index is None:
            raise InputError(f"{path}: record {k} names no frame (give its timestamp_s or its index)")
        line = record_json(record)
        _parse_line(line, f"{path}: record {k}", checks)
        lines.append(json.dumps(line, allow_nan=False, separators=(",", ":")))
    write_text_atomic(path, "".join(f"{line}\n" for line in lines))
    return len(lines)


# ------------------------------------------------------------------------------------------ the reader


@dataclass(frozen=True)
class FileDetection(Detection):
    """A detection read from a file: its (R,) COCO mask runs (None: box only) and (D,) embedding (None: label only)."""

    mask_runs: np.ndarray | None = None
    embedding: np.ndarray | None = None


@dataclass
class _Checks:
    """What a line is checked against: image size, embedding width, frame times and indices (None: not checked)."""

    width: int | None = None
    height: int | None = None
    embedding_dim: int | None = None
    encoder: str = ""
    timestamps_s: np.ndarray | None = None
    indices: np.ndarray | None = None
    first_dim_line: str = ""


@dataclass
class DetectionsTable:
    """A checked detections file: the detections of each frame it names, by that frame's `timestamp_s`.

    `timestamps_s` (F,) sorted frame times, `detections` one list per time; `lines` the file's line numbers kept,
    `dropped_lines` the ones naming no frame of the sequence (only with `unknown_frames="drop"`).
    """

    path: Path
    timestamps_s: np.ndarray
    detections: list[list[FileDetection]]
    lines: list[int] = field(default_factory=list)
    dropped_lines: list[int] = field(default_factory=list)
    embedding_dim: int | None = None

    def at(self, timestamp_s: float) -> list[FileDetection]:
        """The detections of the frame stamped `timestamp_s` (none when the file does not mention it)."""
        i = int(np.searchsorted(self.timestamps_s, timestamp_s))
        for j in (i - 1, i):
            if 0 <= j < len(self.timestamps_s) and abs(self.timestamps_s[j] - timestamp_s) <= TIMESTAMP_TOLERANCE_S:
                return self.detections[j]
        return []

    @property
    def n_detections(self) -> int:
        return sum(len(d) for d in self.detections)

    def summary(self) -> str:
        """One line: detections, frames, how many come with a mask and with an embedding."""
        masks = sum(d.mask_runs is not None for ds in self.detections for d in ds)
        embeddings = sum(d.embedding is not None for ds in self.detections for d in ds)
        return (
            f"{self.n_detections} detections in {len(self.detections)} frames, {masks} with a mask, "
            f"{embeddings} with an embedding"
        )


def read_detections(
    path: str | Path,
    timestamps_s: np.ndarray,
    indices: np.ndarray,
    intrinsics: CameraIntrinsics,
    embedding_dim: int | None = None,
    encoder: str = "",
    unknown_frames: Literal["error", "drop"] = "error",
) -> DetectionsTable:
    """Read and check a detections file against a sequence's (N,) frame times and indices and its camera.

    `embedding_dim` is the width of the prior's embeddings (its text encoder `encoder`); None checks only that every
    embedding has the same width. A line naming no frame of the sequence is an InputError, or with
    `unknown_frames="drop"` left out (a file written for every frame of a recording whose keyframes were kept). Every
    problem is one InputError naming the file and line; the whole file is checked before anything else is done.
    """
    path = Path(path)
    check_detections_file(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not UTF-8 text (byte {exc.start}); a detections file is JSON Lines") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot be read ({exc.strerror or exc.__class__.__name__})") from None
    order = np.argsort(np.asarray(timestamps_s, float), kind="stable")
    checks = _Checks(
        intrinsics.width,
        intrinsics.height,
        embedding_dim,
        encoder,
        np.asarray(timestamps_s, float)[order],
        np.asarray(indices, np.int64)[order],
    )
    by_time: dict[float, tuple[int, list[FileDetection]]] = {}
    kept, dropped = [], []
    for number, raw in enumerate(text.splitlines(), start=1):
        if not raw.strip():
            continue
        where = f"{path} line {number}"
        try:
            line = json.loads(raw)
        except json.JSONDecodeError as exc:
            raise InputError(f"{where}: not JSON ({exc.msg} at column {exc.colno})") from None
        if not isinstance(line, dict):
            raise InputError(f'{where}: a line must be a JSON object with "timestamp" (or "frame") and "detections"')
        row, detections = _parse_line(line, where, checks)
        if row is None:
            if unknown_frames == "error":
                raise InputError(f"{where}: {_no_frame(line, checks)}")
            dropped.append(number)
            continue
        t = float(checks.timestamps_s[row])
        if t in by_time:
            raise InputError(f"{where}: frame at {t!r} s was given already on line {by_time[t][0]}")
        by_time[t] = (number, detections)
        kept.append(number)
    if dropped and not kept:
        raise InputError(f"{path}: no line names a frame of the sequence ({len(dropped)} lines; {_span(checks)})")
    times = sorted(by_time)
    if dropped:
        log.info("%s: %d lines name frames the sequence does not keep; left out", path, len(dropped))
    return DetectionsTable(
        path,
        np.asarray(times, float),
        [by_time[t][1] for t in times],
        kept,
        dropped,
        checks.embedding_dim,
    )


def _span(checks: _Checks) -> str:
    assert checks.timestamps_s is not None and checks.indices is not None
    return (
        f"its frames are stamped {checks.timestamps_s[0]!r} … {checks.timestamps_s[-1]!r} s, "
        f"indices {int(checks.indices.min())} … {int(checks.indices.max())}"
    )


def _no_frame(line: dict, checks: _Checks) -> str:
    if "timestamp" in line:
        tolerance_ms = TIMESTAMP_TOLERANCE_S * 1e3
        return f"timestamp {line['timestamp']!r} matches no frame within {tolerance_ms:g} ms ({_span(checks)})"
    return f"frame {line['frame']!r} is not in the sequence ({_span(checks)})"


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _frame_row(line: dict, where: str, checks: _Checks) -> int | None:
    """The sorted row of the frame a line names (None: no frame of the sequence; -1: not checked)."""
    has_time, has_frame = "timestamp" in line, "frame" in line
    if not has_time and not has_frame:
        raise InputError(f"{where}: missing key 'timestamp' (the colour image's stamp in seconds) or 'frame'")
    if has_time and (not _number(line["timestamp"]) or not math.isfinite(line["timestamp"])):
        raise InputError(f"{where}: timestamp {line['timestamp']!r} is not a finite number of seconds")
    if has_frame and (isinstance(line["frame"], bool) or not isinstance(line["frame"], int) or line["frame"] < 0):
        raise InputError(f"{where}: frame {line['frame']!r} is not a frame index (a whole number ≥ 0)")
    if checks.timestamps_s is None or checks.indices is None:
        return -1
    by_time = by_index = None
    if has_time:
        times, t = checks.timestamps_s, float(line["timestamp"])
        i = int(np.searchsorted(times, t))
        near = [j for j in (i - 1, i) if 0 <= j < len(times)]
        best = min(near, key=lambda j: abs(times[j] - t)) if near else None
        by_time = best if best is not None and abs(times[best] - t) <= TIMESTAMP_TOLERANCE_S else None
    if has_frame:
        matches = np.flatnonzero(checks.indices == int(line["frame"]))
        by_index = int(matches[0]) if len(matches) else None
    if has_time and has_frame and by_time != by_index and by_time is not None and by_index is not None:
        raise InputError(
            f"{where}: timestamp {line['timestamp']!r} and frame {line['frame']} name two different frames"
        )
    return by_time if has_time else by_index


def _parse_line(line: dict, where: str, checks: _Checks) -> tuple[int | None, list[FileDetection]]:
    """The frame row a line names and its checked detections; InputError naming `where` for anything amiss."""
    row = _frame_row(line, where, checks)
    if "detections" not in line:
        raise InputError(f"{where}: missing key 'detections' (a list; [] for a frame with none)")
    entries = line["detections"]
    if not isinstance(entries, list):
        raise InputError(f"{where}: 'detections' must be a list, not {type(entries).__name__}")
    if len(entries) > MAX_DETECTIONS:
        raise InputError(
            f"{where}: {len(entries)} detections in one frame, more than {MAX_DETECTIONS}; keep a detector's best"
        )
    return row, [_parse_detection(entry, f"{where}, detection {k}", checks) for k, entry in enumerate(entries)]


def _parse_detection(entry: Any, where: str, checks: _Checks) -> FileDetection:
    if not isinstance(entry, dict):
        raise InputError(f'{where}: a detection must be a JSON object with "label", "score" and "box"')
    for key in ("label", "score", "box"):
        if key not in entry:
            raise InputError(f"{where}: missing key '{key}'")
    label = entry["label"]
    if not isinstance(label, str) or not label.strip():
        raise InputError(f"{where}: label {label!r} is not a non-empty text")
    score = entry["score"]
    if not _number(score) or not 0.0 <= score <= 1.0:
        raise InputError(f"{where}: score {score!r} is not a number in [0, 1]")
    box = _parse_box(entry["box"], where, checks)
    mask_runs = _parse_mask(entry["mask"], where, checks) if entry.get("mask") is not None else None
    embedding = _parse_embedding(entry["embedding"], where, checks) if entry.get("embedding") is not None else None
    return FileDetection(box, label.strip(), float(score), float(score), None, mask_runs, embedding)


def _parse_box(box: Any, where: str, checks: _Checks) -> np.ndarray:
    if not isinstance(box, list) or len(box) != 4 or not all(_number(v) for v in box):
        raise InputError(f"{where}: box {box!r} is not [x0, y0, x1, y1] in pixels")
    x0, y0, x1, y1 = (float(v) for v in box)
    if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
        raise InputError(f"{where}: box {box!r} is not finite")
    if x1 <= x0 or y1 <= y0:
        raise InputError(f"{where}: box {box!r} is inverted or empty (x1 must exceed x0, y1 must exceed y0)")
    if checks.width is not None and checks.height is not None:
        w, h, s = checks.width, checks.height, BOX_SLACK_PX
        if x0 < -s or y0 < -s or x1 > w + s or y1 > h + s:
            raise InputError(f"{where}: box {box!r} lies outside the {w}x{h} image")
        x0, x1 = min(max(x0, 0.0), w), min(max(x1, 0.0), w)
        y0, y1 = min(max(y0, 0.0), h), min(max(y1, 0.0), h)
        if x1 <= x0 or y1 <= y0:
            raise InputError(f"{where}: box {box!r} lies outside the {w}x{h} image")
    return np.array([x0, y0, x1, y1])


def _parse_mask(mask: Any, where: str, checks: _Checks) -> np.ndarray:
    if not isinstance(mask, dict) or "size" not in mask or "counts" not in mask:
        raise InputError(f'{where}: mask must be COCO RLE {{"size": [height, width], "counts": ...}}')
    size = mask["size"]
    if not isinstance(size, list) or len(size) != 2 or not all(isinstance(v, int) and v > 0 for v in size):
        raise InputError(f"{where}: mask size {size!r} is not [height, width]")
    if checks.width is not None and size != [checks.height, checks.width]:
        raise InputError(
            f"{where}: mask size {size} (height, width) is not the image's [{checks.height}, {checks.width}]"
        )
    counts = mask["counts"]
    if not isinstance(counts, str | list):
        raise InputError(f"{where}: mask counts must be a COCO compressed string or a list of run lengths")
    try:
        runs = rle_runs(counts)
    except ValueError as exc:
        raise InputError(f"{where}: mask does not decode: {exc}") from None
    if len(runs) and int(runs.max()) > size[0] * size[1]:
        raise InputError(f"{where}: mask counts hold a run of {int(runs.max())} pixels, its size {size} has fewer")
    if int(runs.sum()) != size[0] * size[1]:
        covered, pixels = int(runs.sum()), size[0] * size[1]
        raise InputError(f"{where}: mask counts cover {covered} pixels, its size {size} has {pixels}")
    return runs


def _parse_embedding(values: Any, where: str, checks: _Checks) -> np.ndarray:
    if not isinstance(values, list) or not values or not all(_number(v) for v in values):
        raise InputError(f"{where}: embedding is not a list of numbers")
    vector = np.asarray(values, np.float64)
    if not np.all(np.isfinite(vector)):
        raise InputError(f"{where}: embedding holds a value that is not finite")
    if checks.embedding_dim is not None and len(vector) != checks.embedding_dim:
        source = (
            f"the prior's text encoder ({checks.encoder}) gives {checks.embedding_dim}"
            if checks.encoder
            else f"{checks.first_dim_line} has {checks.embedding_dim}"
        )
        raise InputError(f"{where}: embedding has {len(vector)} values, {source}")
    if checks.embedding_dim is None:
        checks.embedding_dim, checks.first_dim_line = len(vector), where.split(", detection")[0]
    largest = float(np.abs(vector).max())
    if largest == 0.0:
        raise InputError(f"{where}: embedding is all zeros (it has no direction to compare)")
    if abs(float(np.linalg.norm(vector / largest)) * largest - 1.0) <= UNIT_TOLERANCE:
        return vector.astype(np.float32)  # a unit vector already: kept as written, bit for bit
    scaled = vector / largest  # no overflow in the norm of values up to 1.8e308, no underflow of tiny ones
    return (scaled / np.linalg.norm(scaled)).astype(np.float32)


def check_detections_file(path: Path) -> None:
    """InputError unless `path` is a regular file: a folder, a device or a missing file each said as such."""
    if path.is_dir():
        raise InputError(f"{path}: is a folder, not a detections file (a JSON-lines file, docs/perception.md)")
    if path.exists() and not path.is_file():
        raise InputError(f"{path}: is not a regular file (a device or a pipe), not a detections file")
    if not path.is_file():
        raise InputError(f"no such detections file: {path}")


def attach_detections(
    sequence_dir: str | Path, source: str | Path, unknown_frames: Literal["error", "drop"] = "error"
) -> DetectionsTable:
    """Check a detections file against the sequence folder `sequence_dir` and copy it in as `detections.jsonl`.

    With `unknown_frames="drop"` lines naming frames the sequence does not hold (frames its keyframe selection left
    out) are left out of the copy. Call it inside the `io.atomic.output_dir` block that writes the folder (as a
    converter does), so the folder's marker lists the file. InputError for a file that does not check.
    """
    from bimfactor.io.sequence import read_sequence

    sequence = read_sequence(sequence_dir)
    table = read_detections(
        source,
        sequence.timestamps(),
        sequence.indices(),
        sequence.meta.intrinsics,
        unknown_frames=unknown_frames,
    )
    lines = Path(source).read_text(encoding="utf-8-sig").splitlines()
    write_text_atomic(Path(sequence_dir) / DETECTIONS_FILE, "".join(f"{lines[n - 1]}\n" for n in table.lines))
    return table


# ------------------------------------------------------------------------------------------ the backend


class FileDetector:
    """The detections a file gives for each frame, faced with the paper's thresholds (the score is both scores)."""

    def __init__(self, table: DetectionsTable, box_threshold: float, text_threshold: float) -> None:
        self.table = table
        self.box_threshold = box_threshold
        self.text_threshold = text_threshold

    def detect(self, frame: Frame) -> list[Detection]:
        """The file's detections of this frame (matched by its timestamp) that pass both thresholds."""
        return [
            d for d in self.table.at(frame.timestamp_s) if passes_thresholds(d, self.box_threshold, self.text_threshold)
        ]


def detection_records(
    frames: Iterable[Frame],
    perceive: Callable[[Frame], tuple[list[Detection], np.ndarray, np.ndarray]],
    with_embeddings: bool = True,
) -> Iterator[FrameRecord]:
    """A detections file's records of `frames`, from `perceive(frame) → (detections, (N, H, W) masks, (N, D)
    embeddings)` (a `Perception.perceive`): label, box score, box, mask and, `with_embeddings`, the embedding."""
    for frame in frames:
        detections, masks, embeddings = perceive(frame)
        yield FrameRecord(
            [
                DetectionRecord(d.label, d.box_score, d.box_xyxy, masks[k], embeddings[k] if with_embeddings else None)
                for k, d in enumerate(detections)
            ],
            timestamp_s=frame.timestamp_s,
        )
