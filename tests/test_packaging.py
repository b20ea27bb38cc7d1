"""The package as a user gets it: a wheel installed into a fresh environment outside the source tree."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
import venv
from pathlib import Path

import pytest
from conftest import ROOT


def run(cmd: list, cwd: Path, env: dict | None = None, timeout: int = 600) -> subprocess.CompletedProcess:
    res = subprocess.run(
        [str(c) for c in cmd], cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout
    )
    assert res.returncode == 0, f"{cmd}\n{res.stdout[-2000:]}\n{res.stderr[-3000:]}"
    return res


@pytest.mark.slow
@pytest.mark.heavy
def test_the_installed_wheel_runs_the_quick_job_and_the_demo_outside_the_source_tree(tmp_path):
    dist = tmp_path / "dist"
    run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", ROOT, "-w", dist],
        tmp_path,
    )
    (wheel,) = dist.glob("layoutwarp-*.whl")
    # a fresh environment; its dependencies (torch & co.) come from this one through a .pth line
    # (the directory is added to sys.path, but the editable install's own .pth there is not read)
    env_dir = tmp_path / "env"
    venv.create(env_dir, with_pip=False, symlinks=os.name != "nt")
    python = env_dir / ("Scripts/python.exe" if os.name == "nt" else "bin/python")
    site = Path(
        run(
            [python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp_path
        ).stdout.strip()
    )
    deps = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}
    (site / "_layoutwarp_test_deps.pth").write_text("\n".join(sorted(deps)) + "\n")
    run([sys.executable, "-m", "pip", "--python", python, "install", "-q", "--no-deps", wheel], tmp_path)
    work = tmp_path / "work"  # far from the checkout: no data_samples/ beside it
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "LAYOUTWARP_DATA")}
    # the torch path: the installed copy's kernels would compile from an empty cache (a minute and a
    # half here, what tests/test_jit.py covers); this test is about what the wheel holds and runs
    env["LAYOUTWARP_JIT"] = "off"
    where = run([python, "-c", "import layoutwarp; print(layoutwarp.__file__)"], work, env).stdout.strip()
    assert Path(where).is_relative_to(site) and not Path(where).is_relative_to(ROOT)
    cli = env_dir / ("Scripts/layoutwarp.exe" if os.name == "nt" else "bin/layoutwarp")
    argv = ["train", "mnist", "--quick", "--epochs", "1", "--family", "curv", "--no-progress", "--out", "q"]
    out = run([cli, *argv], work, env).stdout
    assert "bundled" in out and (work / "q" / "results.json").exists()
    result = json.loads((work / "q" / "results.json").read_text())
    assert Path(result["data"]).is_relative_to(site)  # the samples shipped inside the package
    shipped = site / "layoutwarp" / "data_samples"  # the deepest ones too (Cityscapes' layout)
    assert len(list((shipped / "cityscapes" / "gtFine" / "val" / "frankfurt").glob("*_labelIds.png"))) == 2
    assert (shipped / "celeba" / "list_eval_partition.txt").is_file()
    run([cli, "demo", "--size", "16x12", "--out", "d"], work, env)
    assert (work / "d" / "layouts.png").stat().st_size > 10_000
    # without the samples' flag, the full data is asked for in one line
    res = subprocess.run(
        [str(cli), "train", "mnist", "--no-progress"], cwd=work, env=env, capture_output=True, text=True
    )
    assert res.returncode == 2 and "LAYOUTWARP_DATA" in res.stderr and "Traceback" not in res.stderr
