"""bench buildings on Ray: an instance of its own without --address, whatever an earlier cluster left behind; a
cluster that cannot be reached is one line and exit 2, in bounded time, before any prior is built."""

from __future__ import annotations

import json
import shutil
import socket
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from typer.testing import CliRunner

from bimfactor.cli import app

SHORT = [
    "--variant", "smcl",
    "--set", "evaluation.num_trajectories=1", "--set", "evaluation.repeats=1",
    "--set", "evaluation.trajectory_length=4", "--set", "evaluation.warmup_max_steps=2",
]  # fmt: skip


@pytest.fixture
def ray_tmpdir(monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A Ray temp folder of the test's own, short (Ray's socket paths must fit 107 characters)."""
    folder = Path(tempfile.mkdtemp(prefix="bfray", dir="/tmp"))
    monkeypatch.setenv("RAY_TMPDIR", str(folder))
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


def _closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_without_address_the_bench_runs_on_its_own_ray_instance_despite_a_dead_cluster(
    paper_floor_prior: Path, cli_config_args: list[str], tmp_path: Path, ray_tmpdir: Path, monkeypatch
) -> None:
    pytest.importorskip("ray")
    dead = f"127.0.0.1:{_closed_port()}"
    (ray_tmpdir / "ray").mkdir()
    (ray_tmpdir / "ray" / "ray_current_cluster").write_text(dead)  # what `ray start` left, never `ray stop`ped
    monkeypatch.setenv("RAY_ADDRESS", dead)  # set for some other program
    out = tmp_path / "bench"
    ifc = paper_floor_prior.parent / "paper-floor.ifc"
    started = time.monotonic()
    result = CliRunner().invoke(
        app, ["bench", "buildings", str(ifc), "-o", str(out), "--workers", "1", *SHORT, *cli_config_args]
    )
    elapsed = time.monotonic() - started
    assert result.exit_code == 0, result.output
    # a dead cluster made it retry for minutes; a clean run of these four steps takes seconds
    assert elapsed < 120, elapsed
    assert result.stdout.startswith("runs on: a Ray instance of its own")
    runner = json.loads((out / "results.json").read_text())["runner"]
    assert runner["name"] == "ray" and runner["own_instance"] and runner["address"] is None
    assert runner["nodes"] == 1 and runner["cpus"] == 1


class _SilentServer:
    """A TCP port that accepts connections and never says a word: an address that is no Ray head."""

    def __init__(self) -> None:
        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(64)
        self.port = self.sock.getsockname()[1]
        self.held: list[socket.socket] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            self.held.append(conn)

    def close(self) -> None:
        for conn in self.held:
            conn.close()
        self.sock.close()


def test_an_unreachable_address_is_one_line_and_exit_2_in_bounded_time(
    tmp_path: Path, ray_tmpdir: Path, monkeypatch
) -> None:
    pytest.importorskip("ray")
    from bimfactor.evaluation import paper

    monkeypatch.setattr(paper, "CLUSTER_ANSWER_S", 3.0)
    silent = _SilentServer()
    try:
        for address, message in (
            (f"127.0.0.1:{_closed_port()}", "nothing answers there (ConnectionRefusedError"),
            (f"127.0.0.1:{silent.port}", "the Ray cluster did not answer within 3 s"),
            ("auto", "no Ray cluster answers there"),  # no cluster was ever started with this temp folder
        ):
            started = time.monotonic()
            result = CliRunner().invoke(app, ["bench", "buildings", "paper-floor", "-o", str(tmp_path / "out"),
                                              "--address", address])  # fmt: skip
            elapsed = time.monotonic() - started
            assert result.exit_code == 2, result.output
            lines = result.stderr.strip().splitlines()
            assert len(lines) == 1 and f"--address {address}" in lines[0] and message in lines[0], lines
            assert elapsed < 3.0 + 10, elapsed
            assert not (tmp_path / "out").exists()  # before any prior
    finally:
        silent.close()
