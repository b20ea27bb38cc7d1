"""Atomic writes: a failed write leaves the old file, no temporary files, the usual file mode."""

from __future__ import annotations

import pytest
import torch

from layoutwarp.files import atomic_write

F64 = torch.float64


def test_atomic_write_leaves_old_file_on_failure(tmp_path, monkeypatch):
    target = tmp_path / "out.png"
    target.write_bytes(b"old")

    def boom(*args):
        raise OSError("disk full")

    monkeypatch.setattr("os.replace", boom)
    with pytest.raises(OSError):
        atomic_write(target, b"new contents")
    assert target.read_bytes() == b"old" and list(tmp_path.iterdir()) == [target]


def test_atomic_write_gives_the_usual_mode_and_leaves_no_temporary_files(tmp_path):
    import os

    path = atomic_write(tmp_path / "sub" / "a.txt", "hello")
    assert path.read_text() == "hello" and [p.name for p in path.parent.iterdir()] == ["a.txt"]
    mask = os.umask(0)
    os.umask(mask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~mask
    atomic_write(path, lambda tmp: open(tmp, "w").write("by a writer"))
    assert path.read_text() == "by a writer"


def test_importing_the_package_changes_no_global_state():
    import subprocess
    import sys

    code = (
        "import os, sys, torch; mask = os.umask(0o027); threads = torch.get_num_threads(); "
        "import layoutwarp, layoutwarp.experiments.plots, layoutwarp.experiments.bench; "
        "assert os.umask(0o022) == 0o027; assert torch.get_num_threads() == threads; "
        "assert 'matplotlib.pyplot' not in sys.modules; "
        "assert 'kornia' not in sys.modules and 'scipy.sparse' not in sys.modules; print('ok')"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.stdout.strip() == "ok", res.stderr[-2000:]
