"""MkDocs hook: the figures and measured outputs under examples/ are part of the site, at the
same relative paths the README uses, so one link works in both."""

from __future__ import annotations

from pathlib import Path

from mkdocs.structure.files import File, Files

SUFFIXES = {".png", ".txt", ".json"}


def on_files(files: Files, config) -> Files:
    root = Path(config["docs_dir"]).parent
    for path in sorted((root / "examples").rglob("*")):
        if path.is_file() and path.suffix in SUFFIXES:
            files.append(File.generated(config, path.relative_to(root).as_posix(), abs_src_path=str(path)))
    return files
