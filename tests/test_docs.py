"""The documentation site builds with --strict: broken references and links fail."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from conftest import ROOT


@pytest.mark.slow
def test_the_docs_build_strictly(tmp_path):
    pytest.importorskip("mkdocs", reason="the docs extra is not installed (pip install -e '.[docs]')")
    pytest.importorskip("mkdocstrings")
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    cmd = [
        sys.executable,
        "-m",
        "mkdocs",
        "build",
        "--strict",
        "-f",
        str(ROOT / "mkdocs.yml"),
        "-d",
        str(tmp_path),
    ]
    res = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT, timeout=600)
    assert res.returncode == 0, res.stderr[-4000:]
    api = (tmp_path / "api" / "index.html").read_text()
    for name in ("simulate", "SensorLayer", "SensorPhysics", "integrate_exact", "labels_to_sensor"):
        assert name in api, name
    assert (tmp_path / "examples" / "study" / "mnist" / "study_mnist.png").exists()  # the README's figures
    assert not (tmp_path / "hooks.py").exists()


@pytest.mark.parametrize("page", ["README.md", "docs/index.md", "docs/learn.md"])
def test_the_front_pages_python_examples_run(page, tmp_path, monkeypatch):
    import re

    monkeypatch.chdir(tmp_path)  # where an example writes its files
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / page).read_text(), re.S)
    assert blocks
    scope: dict = {}  # a page's blocks build on each other
    for code in blocks:
        exec(compile(code, page, "exec"), scope)


def test_the_api_page_lists_every_public_name():
    import layoutwarp as lw

    api = (ROOT / "docs" / "api.md").read_text()
    missing = [n for n in lw.__all__ if n != "__version__" and f"- {n}\n" not in api and f".{n}\n" not in api]
    assert not missing, missing
