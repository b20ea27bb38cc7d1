"""MkDocs hooks: the figures and measured outputs under examples/ are part of the site, at the
same relative paths the README uses, so one link works in both; and a Sphinx role left in a
docstring (``:func:`x```, which mkdocstrings shows as raw text) is a warning, so the strict
build fails on it. Cross-references are written as mkdocstrings renders them: ``[`name`][]``
(resolved from the docstring's scope) or ``[`name`][full.path]``."""

from __future__ import annotations

import logging
import re
from pathlib import Path

from mkdocs.structure.files import File, Files

SUFFIXES = {".png", ".txt", ".json"}
# a role raw, or as rendered (its backticks become <code>)
ROLE = re.compile(r":(?:func|class|meth|mod|data|attr|exc|obj|ref):(?:`[^`]*`|<code>[^<]*</code>)")
log = logging.getLogger("mkdocs.plugins.layoutwarp")


def on_files(files: Files, config) -> Files:
    root = Path(config["docs_dir"]).parent
    for path in sorted((root / "examples").rglob("*")):
        if path.is_file() and path.suffix in SUFFIXES:
            files.append(File.generated(config, path.relative_to(root).as_posix(), abs_src_path=str(path)))
    return files


def on_page_content(html: str, page, config, files) -> str:
    for role in sorted(set(ROLE.findall(html))):
        log.warning("%s: a raw Sphinx role in a docstring: %s", page.file.src_path, role)
    return html
