"""``tools/bootstrap.sh``: it finds an installed libusb (no false "installing" line) and is silent when the .venv is
already what ``pyproject.toml`` and ``constraints.txt`` ask for."""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_an_installed_libusb_is_found_even_when_the_library_list_is_long(tmp_path: Path) -> None:
    """``ldconfig -p`` lists libusb first and then more than a pipe buffer of other libraries: a ``grep -q`` that stops
    early kills ldconfig with SIGPIPE, which ``set -o pipefail`` read as 'not installed'. The bootstrap must find it,
    print nothing and never call apt-get."""
    repo = tmp_path / "repo"
    (repo / "tools").mkdir(parents=True)
    shutil.copy(ROOT / "tools" / "bootstrap.sh", repo / "tools" / "bootstrap.sh")
    for name in ("pyproject.toml", "constraints.txt"):
        shutil.copy(ROOT / name, repo / name)
    stamp = hashlib.sha256((repo / "pyproject.toml").read_bytes() + (repo / "constraints.txt").read_bytes())
    (repo / ".venv").mkdir()
    (repo / ".venv" / ".mpchair-installed").write_text(stamp.hexdigest()[:16] + "\n")
    fake = tmp_path / "bin"
    fake.mkdir()
    (fake / "ldconfig").write_text(
        "#!/bin/bash\necho '\tlibusb-1.0.so.0 (libc6,x86-64) => /usr/lib/x86_64-linux-gnu/libusb-1.0.so.0'\n"
        "for i in $(seq 1 20000); do echo \"\tlibfake$i.so.1 (libc6,x86-64) => /usr/lib/libfake$i.so.1\"; done\n")
    (fake / "apt-get").write_text(f"#!/bin/bash\ntouch {tmp_path / 'apt-get-called'}\n")
    for f in fake.iterdir():
        f.chmod(0o755)
    env = {**os.environ, "PATH": f"{fake}:{os.environ['PATH']}"}
    res = subprocess.run(["bash", str(repo / "tools" / "bootstrap.sh")], capture_output=True, text=True, env=env,
                         timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout == "" and not (tmp_path / "apt-get-called").exists(), res.stdout
