"""A real, non-editable install: build the wheel, install it into a fresh venv, run the CLI.

The wheel is built from a copy of the sources (so the checkout is not touched by a parallel run);
the fresh venv has no pip and reaches the dependencies through a path line to this venv's
site-packages (a path line runs no ``.pth`` file, so the editable ``cdpr`` of this venv is not
visible there): only the wheel provides ``cdpr``.  Every command runs from an empty folder.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("analysis", "calibration", "daq", "pipelines")


def _run(cmd: list[str], cwd: Path, timeout: float = 600.0) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "CAN_"))}
    env["HOME"] = str(cwd)  # no ~/.canrc or ~/can.conf of the user
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, f"{cmd}: exit {r.returncode}\n{r.stdout}\n{r.stderr}"
    return r


def test_wheel_installs_and_runs_the_cli_smoke_commands(tmp_path):
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, src / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    for pkg in PACKAGES:
        shutil.copytree(ROOT / pkg, src / pkg, ignore=ignore)
    wheels = tmp_path / "wheels"
    _run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(wheels), str(src)],
        tmp_path,
    )
    (wheel,) = wheels.glob("cdpr-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    assert "cdpr/daq/loadcell.dbc" in names  # every data file the code loads is package data
    assert not any(n.startswith(("tests/", "data_samples/")) for n in names)

    venv = tmp_path / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], tmp_path)
    py = venv / "bin" / "python"
    site = Path(
        _run(
            [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp_path
        ).stdout.strip()
    )
    (site / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    _run(
        [
            sys.executable,
            "-m",
            "pip",
            "--python",
            str(py),
            "install",
            "-q",
            "--no-deps",
            "--no-index",
            str(wheel),
        ],
        tmp_path,
    )

    work = tmp_path / "work"
    work.mkdir()
    cdpr = str(venv / "bin" / "cdpr")
    probe = "import cdpr.daq.can_dbc as c; print(c.__file__); print(c.DEFAULT_DBC.is_file())"
    where, dbc_ok = _run([str(py), "-c", probe], work).stdout.split()
    assert Path(where).is_relative_to(site) and dbc_ok == "True"
    assert _run([cdpr, "--version"], work).stdout.startswith("cdpr ")
    _run([cdpr, "rig", "paper", "--out", "rigs"], work)
    _run([cdpr, "rig", "show", "rigs/flat_optimum.toml"], work)
    _run([cdpr, "solve", "--rig", "rigs/flat_optimum.toml", "--out", "t.csv"], work)
    tensions = pd.read_csv(work / "t.csv", comment="#")
    assert tensions["feasible"].tolist() == [1]
    # the virtual rig over python-can with the packaged DBC, then the run read back
    schedule = str(ROOT / "data_samples" / "schedule_demo.toml")
    _run(
        [cdpr, "simulate", "--rig", "rigs/flat_optimum.toml", "--schedule", schedule,
         "--duration", "1", "--speed", "4", "--quiet", "--out", "runs"],
        work,
    )  # fmt: skip
    (run,) = (work / "runs").glob("*.mcap")
    report = _run([cdpr, "inspect", str(run)], work).stdout
    assert "tension" in report.lower()
    truth = np.load(next((work / "runs").glob("*.truth.npz")))
    assert len(truth.files) > 0
