"""bench buildings on Ray: an instance of its own without --address, whatever an earlier cluster left behind; a
cluster that cannot be reached is one line and exit 2, in bounded time, before any prior is built; on a real cluster
of two nodes (`ray.cluster_utils.Cluster`, on this machine) the runs spread over both, equal the process pool's, and
survive a node dying mid-run, and runs lost for good are named in one line, exit 1."""

from __future__ import annotations

import contextlib
import json
import shutil
import socket
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import astuple
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from typer.testing import CliRunner

from bimfactor.cli import app
from bimfactor.config import load_config
from tests.cli import assert_one_line_error

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


TINY = [
    "evaluation.num_trajectories=4", "evaluation.repeats=1", "evaluation.trajectory_length=4",
    "evaluation.warmup_max_steps=2", "evaluation.variants=[smcl]",
]  # fmt: skip


@pytest.fixture
def two_node_cluster(ray_tmpdir: Path) -> Iterator[Any]:
    """A Ray cluster of a head and a second node, 1 CPU each, on this machine, this process its driver; stopped (its
    processes only) at the end."""
    pytest.importorskip("ray")
    import ray
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    try:
        cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        cluster.connect()
        yield cluster
    finally:
        ray.shutdown()
        cluster.shutdown()


class _WhenARunStartsOn:
    """Watches a node's worker processes from a thread: the first to run a benchmark run (its title
    `ray::_run_one_on_ray`) is given to `action` (a psutil.Process), and `fired` is set once `action` returned."""

    def __init__(self, node: Any, action: Callable[[Any], None]) -> None:
        import psutil

        self.raylet = psutil.Process(node.all_processes["raylet"][0].process.pid)
        self.action = action
        self.fired, self._stop = threading.Event(), threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)
        self._thread.start()

    def _watch(self) -> None:
        import psutil

        while not self._stop.is_set():
            try:
                children = self.raylet.children(recursive=True)
            except psutil.Error:  # the node is gone
                return
            for child in children:
                try:
                    running = child.cmdline()[:1] == ["ray::_run_one_on_ray"]
                except psutil.Error:
                    continue
                if running:
                    self.action(child)
                    self.fired.set()
                    return
            time.sleep(0.02)

    def stop(self) -> bool:
        """Stop watching (after an action under way has returned); whether it fired."""
        self._stop.set()
        self._thread.join()
        return self.fired.is_set()


def _assert_same_runs(mine: list, theirs: list) -> None:
    """The runs of two runners, array for array, and their metrics but time (the node that ran a run is no part of
    its result)."""
    assert [len(runs) for runs in mine] == [len(runs) for runs in theirs]
    for a, b in zip([r for runs in mine for r in runs], [r for runs in theirs for r in runs], strict=True):
        assert (a.variant, a.trajectory, a.repeat) == (b.variant, b.trajectory, b.repeat)
        for name in ("trans_err_m", "orient_err_deg", "room_hit", "inside_ellipse95", "storey_hit"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        timeless = [{k: v for k, v in r.metrics.items() if k != "step_ms_median"} for r in (a, b)]
        assert timeless[0] == timeless[1]  # every metric but the step time
        np.testing.assert_equal(astuple(a.outcome), astuple(b.outcome))  # NaN equals NaN here


def test_on_a_two_node_cluster_runs_spread_equal_the_pool_and_survive_a_node_dying(
    paper_floor_prior: Path, config_overrides: list[str], cli_config_args: list[str], two_node_cluster: Any,
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:  # fmt: skip
    from bimfactor.bim.prior import BimPrior
    from bimfactor.bim.symmetry import twin_motions
    from bimfactor.evaluation import buildings, paper
    from bimfactor.evaluation.paper import paper_jobs, run_jobs

    cfg = load_config(None, [*config_overrides, *TINY])
    jobs = paper_jobs(paper_floor_prior, cfg, twin_motions(BimPrior.load(paper_floor_prior)))
    local = run_jobs(jobs, "local", "processes", workers=1)
    assert {r.node for runs in local for r in runs} == {""}
    cluster = two_node_cluster
    (worker,) = cluster.worker_nodes
    head_id, worker_id = cluster.head_node.node_id, worker.node_id

    where: dict = {}
    spread = run_jobs(jobs, "cluster", "ray", where=where)
    _assert_same_runs(local, spread)
    assert {r.node for runs in spread for r in runs} == {head_id, worker_id}
    assert (where["nodes"], where["cpus"]) == (2, 2)
    assert set(where["runs_per_node"]) == {head_id, worker_id} and sum(where["runs_per_node"].values()) == 4

    # The second node dies while it runs one: the run is run again on the head, no result is lost.
    removal = _WhenARunStartsOn(worker, lambda _: cluster.remove_node(worker))
    survived = run_jobs(jobs, "cluster", "ray")
    assert removal.stop() and worker not in cluster.worker_nodes, "no run started on the second node"
    _assert_same_runs(local, survived)
    assert {r.node for runs in survived for r in runs} == {head_id}

    # Without retries a run whose worker dies is lost: the bench names it in one line and exits 1, writing nothing.
    monkeypatch.setattr(paper, "RAY_TASK_RETRIES", 0)
    monkeypatch.setattr(buildings, "build_priors", lambda chosen, cfg, out: {"paper-floor.ifc": paper_floor_prior})
    kill = _WhenARunStartsOn(cluster.head_node, lambda process: process.kill())
    out = tmp_path / "bench"
    ifc = paper_floor_prior.parent / "paper-floor.ifc"
    args = ["bench", "buildings", str(ifc), "-o", str(out), *cli_config_args, *(a for s in TINY for a in ("--set", s))]
    result = CliRunner().invoke(app, args)  # the Ray session this test connected is used as it is
    assert kill.stop()
    line = assert_one_line_error(result, exit_code=1, contains="1 of 4 runs lost: paper-floor.ifc trajectory ")
    assert "repeat 0 (WorkerCrashedError: the node or worker running each died on every try, 0 retries" in line
    assert not (out / "results.json").exists()


def test_bench_buildings_runs_on_a_cluster_that_ray_start_started(
    paper_floor_prior: Path, cli_config_args: list[str], tmp_path: Path, ray_tmpdir: Path
) -> None:
    """The user's path: `ray start --head` (token authentication on, as Ray 2.5x starts it), then `bench buildings
    --address HOST:PORT`. Only the processes of this cluster (those naming its temp folder) are stopped."""
    pytest.importorskip("ray")
    import subprocess
    import sys

    import psutil

    port = _closed_port()
    ray_cli = Path(sys.executable).parent / "ray"
    started = subprocess.run(
        [str(ray_cli), "start", "--head", f"--port={port}", "--num-cpus=1", "--include-dashboard=false"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    try:
        assert started.returncode == 0, started.stderr[-2000:]
        out = tmp_path / "bench"
        ifc = paper_floor_prior.parent / "paper-floor.ifc"
        result = CliRunner().invoke(
            app,
            ["bench", "buildings", str(ifc), "-o", str(out), "--address", f"127.0.0.1:{port}", *SHORT,
             *cli_config_args],
        )  # fmt: skip
        assert result.exit_code == 0, result.output
        assert result.stdout.startswith(f"runs on: the Ray cluster at 127.0.0.1:{port}\n  1 node(s), 1 CPUs")
        runner = json.loads((out / "results.json").read_text())["runner"]
        assert runner["address"] == f"127.0.0.1:{port}" and not runner["own_instance"] and runner["nodes"] == 1
    finally:
        for process in psutil.process_iter(["cmdline"]):
            if any(str(ray_tmpdir) in part for part in process.info["cmdline"] or []):
                with contextlib.suppress(psutil.Error):
                    process.kill()
