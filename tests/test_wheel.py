"""The wheel works on its own (issue 46): built from the checkout's sources (``pip wheel --no-deps``), installed into a
fresh virtual environment with the pinned dependencies, and run from a folder outside the checkout, it synthesizes a
house, generates frames, trains from a packaged config named without a path, evaluates and exports.

Fast and offline: the wheel is built with this environment's setuptools (``--no-build-isolation``, nothing fetched),
and the fresh environment reuses this one's installed dependencies through a ``.pth`` file pointing at a folder of
links to them (everything but this project's own editable install), so ``pip install --no-index -c constraints.txt``
checks the wheel's requirements against the pins without downloading anything (never a CUDA torch).

It runs in ``make test`` and CI; ``MPCHAIR_SKIP_WHEEL_TEST=1`` (and nothing else) skips it.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest

from detector.config import CONFIG_DIR, available_configs
from detector.pretrained import PRETRAINED_DIR
from mpchair.scan.sensors import SENSOR_DIR, available_sensors

ROOT = Path(__file__).resolve().parents[1]
SKIP_ENV = "MPCHAIR_SKIP_WHEEL_TEST"
pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(os.environ.get(SKIP_ENV) == "1", reason=f"{SKIP_ENV}=1 skips the wheel test")]
#: What the wheel is built from: the project's metadata, its two stacks and the experiment (as a clean clone has them).
SOURCES = ("pyproject.toml", "README.md", "mpchair", "detector", "reproduction")


def _run(args: list, cwd: Path, expect: int = 0) -> subprocess.CompletedProcess:
    """Run ``args`` in ``cwd`` with no PYTHONPATH (nothing may reach the checkout); fail with its output unless it
    exits ``expect``."""
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    proc = subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    command = " ".join(map(str, args))
    assert proc.returncode == expect, f"{command} exited {proc.returncode}:\n{proc.stdout}\n{proc.stderr}"
    return proc


def _link_dependencies(into: Path) -> None:
    """A folder of links to this environment's installed distributions, leaving out this project's own (its editable
    install would lead back into the checkout) and the ``.pth`` hooks."""
    into.mkdir()
    own = ("__editable__", "mpchair-", "mpchair.", "__pycache__")
    for site in sorted({sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}):
        for entry in sorted(Path(site).iterdir()):
            if entry.name.startswith(own) or entry.suffix == ".pth" or (into / entry.name).exists():
                continue
            (into / entry.name).symlink_to(entry)


@pytest.fixture(scope="module")
def wheel_env(tmp_path_factory) -> dict[str, Path]:
    """Build the wheel from a copy of the sources and install it into a fresh venv; the wheel and the venv's bin/."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    for name in SOURCES:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(ROOT / name, src / name)
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q", "-w",
          tmp / "dist", src], cwd=tmp)
    (wheel,) = sorted((tmp / "dist").glob("mpchair-*.whl"))
    env = tmp / "venv"
    venv.create(env, with_pip=False)
    _link_dependencies(tmp / "deps")
    site = Path(_run([env / "bin" / "python", "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                     cwd=tmp).stdout.strip())
    (site / "_mpchair_test_dependencies.pth").write_text(f"{tmp / 'deps'}\n")
    _run([env / "bin" / "python", "-m", "pip", "install", "--no-index", "-q", "-c", ROOT / "constraints.txt",
          wheel], cwd=tmp)
    return {"wheel": wheel, "bin": env / "bin", "site": site, "work": tmp}


def test_the_wheel_holds_what_the_commands_read(wheel_env):
    names = set(zipfile.ZipFile(wheel_env["wheel"]).namelist())
    packaged = {f"detector/configs/{n}.yaml" for n in available_configs()}
    packaged |= {f"mpchair/scan/profiles/{n}.yaml" for n in available_sensors()}
    packaged |= {f"detector/pretrained/{p.name}" for p in PRETRAINED_DIR.iterdir() if p.is_file()}
    packaged.add("mpchair/data/mpcat40.tsv")
    assert packaged <= names, sorted(packaged - names)
    assert len(available_configs()) == 22 and "detector/pretrained/README.md" in names
    assert not any(n.startswith(("tests/", "tools/", "configs/", "docs/")) for n in names)
    # the experiment ships too (one package list serves the editable install), and refuses to run outside a clone
    assert {"reproduction/checkout.py", "reproduction/cli.py", "reproduction/device_check/cli.py"} <= names


def test_the_installed_wheel_generates_trains_evaluates_and_exports_outside_the_checkout(wheel_env):
    bin_, work = wheel_env["bin"], wheel_env["work"] / "user"
    work.mkdir()
    where = _run([bin_ / "python", "-c", "import mpchair, detector.config as c, mpchair.scan.sensors as s; "
                  "print(mpchair.__file__); print(c.CONFIG_DIR); print(s.SENSOR_DIR)"], cwd=work).stdout.split()
    assert all(Path(p).is_relative_to(wheel_env["site"]) for p in where), where
    assert Path(where[1]) != CONFIG_DIR and Path(where[2]) != SENSOR_DIR
    # the help lists the packaged names
    def help_of(*command: str) -> str:
        return " ".join(_run([bin_ / command[0], *command[1:], "--help"], work).stdout.split())

    assert "packaged profile's name (lidar16, lidar64, mp3d-depth90)" in help_of("mpchair", "generate")
    assert f"packaged config's name ({', '.join(available_configs())})" in help_of("detector", "train")

    houses = json.loads(_run([bin_ / "mpchair", "synth", "--out", "houses", "--houses", "1", "--json"], work).stdout)
    (house,) = houses["houses"]
    summary = json.loads(_run([bin_ / "mpchair", "generate", "--root", "houses", "--house", house, "--frames", "6",
                               "--out", "ds", "--quiet", "--json"], work).stdout)
    assert summary["complete"] and summary["frames"] == 6 and summary["splits"]["train"] >= 2
    _run([bin_ / "detector", "train", "--config", "mpchair_sparse_cpu", "--data", "ds", "--out", "run",
          "--max-steps", "2", "--threads", "2", "--no-progress"], work)
    assert (work / "run" / "last.pt").is_file()
    assert "backbone: sparse" in (work / "run" / "config.yaml").read_text()
    ap = json.loads(_run([bin_ / "detector", "eval", "--config", "mpchair_sparse_cpu", "--data", "ds", "--checkpoint",
                          "run/last.pt", "--split", "val", "--threads", "2", "--json"], work).stdout)
    assert set(ap["Chair"]["3d"]) == {"R11", "R40", "overall"} and ap["num_gt_overall"]["Chair"] >= 0
    _run([bin_ / "detector", "export", "--config", "mpchair_sparse_cpu", "--checkpoint", "run/last.pt",
          "--format", "onnx", "--out", "exported"], work)
    deploy = json.loads((work / "exported" / "deploy.json").read_text())
    assert (work / "exported" / "model.onnx").stat().st_size > 100_000 and deploy["weights"] == "run/last.pt"
    # the reproduction, which writes a clone's docs/, says in one line that an installed package is not one
    refused = _run([bin_ / "python", "-c", "from reproduction.cli import main; raise SystemExit(main([]))"],
                   work, expect=2)
    assert refused.stderr.startswith("error: the reproduction runs in a clone of the repository")
    assert len(refused.stderr.strip().splitlines()) == 1
