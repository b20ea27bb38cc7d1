"""The documentation site builds with --strict: broken references and links fail."""

from __future__ import annotations

import os
import re
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
    # cross-references render as links, no Sphinx role as raw text; FAMILIES says what it holds
    assert api.count('class="autorefs autorefs-internal"') > 150  # docstrings link to each other
    assert ":func:" not in api and ":class:" not in api
    text = " ".join(re.sub(r"<[^>]+>", "", api).split())
    assert "FAMILIES = {}" not in text
    assert "uniform, rect, curv, fovea and elliptic (this module), spline and grid" in text


ROLE = re.compile(r":(?:func|class|meth|mod|data|attr|exc|obj):`")


def test_no_docstring_of_the_package_holds_a_sphinx_role():
    """mkdocstrings shows Sphinx roles as raw text: the package writes its cross-references as
    ``[`name`][]`` or ``[`name`][full.path]`` (docs/hooks.py also fails the strict build on one)."""
    found = [
        f"{path.relative_to(ROOT)}:{n}"
        for path in sorted((ROOT / "layoutwarp").rglob("*.py"))
        for n, line in enumerate(path.read_text().splitlines(), 1)
        if ROLE.search(line)
    ]
    assert not found, found


@pytest.mark.parametrize("page", ["README.md", "docs/index.md", "docs/learn.md"])
def test_the_front_pages_python_examples_run(page, tmp_path, monkeypatch):
    import re

    monkeypatch.chdir(tmp_path)  # where an example writes its files
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / page).read_text(), re.S)
    assert blocks
    scope: dict = {}  # a page's blocks build on each other
    for code in blocks:
        exec(compile(code, page, "exec"), scope)


#: What each guide page's fragments take as given (the names its text speaks of), small.
PLACEHOLDERS = {
    "docs/dense.md": """
layer = lw.SensorLayer((18, 24), "curv")
layout, images = layer.layout, torch.rand(2, 3, 360, 480)
net, labels = torch.nn.Conv2d(3, 12, 1), torch.randint(0, 12, (2, 360, 480))
sensor_uint8_hwc = np.random.default_rng(0).integers(0, 256, (18, 24, 3), dtype=np.uint8)
""",
    "docs/families.md": """
control = lw.GridLayout.from_layout(lw.CurvLayout((0.3, 0.2)), grid=(6, 8)).control_points().detach()
src_size = (72, 96)
map_x, map_y = lw.forward_maps(lw.RectLayout((0.3, 0.2)), (12, 16), src_size).numpy()
train_images = torch.rand(4, 1, 72, 96)
""",
    "docs/kornia.md": "",  # runs as written: its inputs are on the page
    "docs/fabrication.md": "",
    "docs/physics.md": """
img, layout = torch.rand(1, 3, 258, 514), lw.CurvLayout((0.3, -0.1))
""",
}


@pytest.mark.parametrize("page", list(PLACEHOLDERS))
def test_the_guides_python_fragments_run_on_placeholders(page, tmp_path, monkeypatch):
    import re

    monkeypatch.chdir(tmp_path)
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / page).read_text(), re.S)
    assert blocks
    scope: dict = {}
    exec("import numpy as np\nimport torch\nimport layoutwarp as lw\n" + PLACEHOLDERS[page], scope)
    for code in blocks:
        exec(compile(code, page, "exec"), scope)


def test_the_api_page_lists_every_public_name():
    import layoutwarp as lw

    api = (ROOT / "docs" / "api.md").read_text()
    missing = [n for n in lw.__all__ if n != "__version__" and f"- {n}\n" not in api and f".{n}\n" not in api]
    assert not missing, missing


def _table_rows(text: str) -> list[tuple[int, list[list[str]]]]:
    """Every Markdown table outside code blocks: (line of its header, its rows' cells), a pipe
    inside a code span not splitting a cell."""
    lines, tables, fenced, i = text.splitlines(), [], False, 0
    while i < len(lines):
        fenced ^= lines[i].startswith("```")
        if (
            not fenced
            and lines[i].startswith("|")
            and i + 1 < len(lines)
            and re.fullmatch(r"\|[\s:|-]+\|", lines[i + 1])
        ):
            rows, j = [lines[i]], i + 2
            while j < len(lines) and lines[j].startswith("|"):
                rows.append(lines[j])
                j += 1
            cells = [
                [c.strip() for c in re.sub(r"`[^`]*`", "code", r).strip().strip("|").split("|")] for r in rows
            ]
            tables.append((i + 1, cells))
            i = j
        else:
            i += 1
    return tables


@pytest.mark.parametrize("page", ["README.md", *sorted(p.name for p in (ROOT / "docs").glob("*.md"))])
def test_every_table_has_a_header_for_each_column_and_rows_of_its_width(page):
    path = ROOT / page if page == "README.md" else ROOT / "docs" / page
    for line, (head, *rows) in _table_rows(path.read_text()):
        assert all(head), f"{page}:{line}: a column without a header: {head}"
        for k, row in enumerate(rows):
            assert len(row) == len(head), f"{page}:{line + 2 + k}: {len(row)} cells under {len(head)} headers"


def test_the_home_pages_figure_says_what_it_shows():
    """The CamVid figure shows the uniform, curvilinear and rectangular layouts; its alt text names
    those, and no other family."""
    for page in ("README.md", "docs/index.md"):
        (alt,) = re.findall(r"!\[([^\]]*)\]\([^)]*camvid_48x36\.png\)", (ROOT / page).read_text())
        for other in ("fovea", "spline", "grid", "elliptic"):
            assert other not in alt.lower(), (page, alt)


#: A repository path as the pages name it: under one of the repository's own folders.
REPO_PATH = re.compile(
    r"(?<![\w./-])(?:\.\./)?((?:layoutwarp|examples|tests|docs|data_samples|\.ci)/[\w./+-]*[\w/])"
)


@pytest.mark.parametrize(
    "page", ["README.md", "CHANGELOG.md", *sorted(f"docs/{p.name}" for p in (ROOT / "docs").glob("*.md"))]
)
def test_every_repository_path_a_page_names_exists(page):
    """A page that names a file or folder of the repository (``examples/gpu_check.py``,
    ``tests/test_docs.py::test_x``, a figure) names one that exists; outputs a command writes
    (under ``results/``, or a file a reader makes) are not repository paths and are not checked.
    The CHANGELOG may name what a version removed."""
    text = (ROOT / page).read_text()
    missing = []
    for match in REPO_PATH.finditer(text):
        path = match.group(1).split("::")[0].split("#")[0].rstrip(".")
        if any(re.fullmatch(r"[A-Z][A-Z_]+", part) for part in path.split("/")):
            continue  # a placeholder (examples/study/TASK)
        if page == "CHANGELOG.md" and path.startswith("layoutwarp/"):
            continue  # removed modules are history there
        if not (ROOT / path).exists():
            missing.append(path)
    assert not missing, f"{page} names paths that do not exist: {sorted(set(missing))}"
