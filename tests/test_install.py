"""The install a user gets from the public index: `pip install '.[ocr]'` (what the README documents beside
tools/setup.sh) resolves no torch and no CUDA package (nvidia-*), since the core never imports torch."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PUBLIC_INDEX = "https://pypi.org/simple"


def test_the_install_from_the_public_index_pulls_no_torch_and_no_cuda(tmp_path: Path) -> None:
    """A dry run with pip's configuration ignored (--isolated: no local wheel folders), PyPI alone."""
    report = tmp_path / "report.json"
    done = subprocess.run(
        [
            sys.executable, "-m", "pip", "install", "--dry-run", "--isolated", "--ignore-installed", "--quiet",
            "--disable-pip-version-check", "--timeout", "20", "--report", str(report), "--index-url", PUBLIC_INDEX,
            f"{ROOT}[ocr]",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )  # fmt: skip
    if done.returncode != 0 and any(
        word in done.stderr.lower() for word in ("connection", "network", "resolve host", "timed out")
    ):
        pytest.skip(f"{PUBLIC_INDEX} cannot be reached: {done.stderr.strip().splitlines()[-1]}")
    assert done.returncode == 0, done.stderr
    names = {item["metadata"]["name"].lower() for item in json.loads(report.read_text())["install"]}
    assert {"bimfactor", "onnxruntime", "tokenizers", "safetensors", "open3d"} <= names
    assert not {n for n in names if n.startswith(("torch", "nvidia-", "triton"))}
    assert "sentence-transformers" not in names
