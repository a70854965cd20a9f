"""Re-run issue 47's ten hostile-input families as real command lines and check each run for what the issue's
done-criterion forbids: a hang, an orphaned process, a user file deleted or rewritten, a traceback, bad input
accepted, partial output left behind, an error longer than one line.

Usage::

    PYTHONPATH=. .venv/bin/python tests/hostile_audit.py                 # every family, one line each
    PYTHONPATH=. .venv/bin/python tests/hostile_audit.py --family threads --json runs.json

Every run is a subprocess of the installed commands (``BIN/mpchair``, ``BIN/detector``, ``BIN/python
tools/reproduce.py``; BIN defaults to the clone's ``.venv/bin``) in its own folder under a temporary work folder,
on tiny inputs built with the tests' helpers (``tests/helpers_detector.py``'s dataset and slim config, a random
checkpoint, ``tests/helpers_recordings.py``'s two-frame stream, a one-house ``mpchair synth``). Each run is checked
for:

- ``hang``: no exit within ``--timeout`` seconds, and again within 5 x that (a starved machine is slow, not hung);
- ``orphan``: a process left in the run's process group (or a child of a killed main process) 10 s after it ended;
- ``deleted``: a planted user file (sha256) or a shared input changed or gone;
- ``traceback``: ``Traceback`` in stderr;
- ``accepted``: exit 0 where a refusal (or a ``warning:`` line) is expected; ``crash``: a signal or an exit other
  than 1 / 2 on a refusal; ``failed``: a non-zero exit where success is expected;
- ``partial``: a refused run changed its folder (new files included), or a run left ``.*.tmp``, ``.OUT.work*``,
  ``.OUT.old*`` or lock files behind;
- ``multiline``: a refusal's stderr is not one ``error:`` line (``warning:`` lines aside, which docs/reliability.md
  allows after a successful run's output only, so they are ignored); ``message``: the line lacks what it must name;
- ``memory``: a run's peak resident memory above ``--max-rss-gib``; ``mismatch``: a resumed run's checkpoints or a
  killed export's folder differ from the uninterrupted run's.

The export over 2 GiB (family 3) is skipped: it needs > 2 GiB of weights written and verified, minutes of CPU; its
check is ``tests/test_owned_outputs.py::test_an_export_whose_weights_lie_outside_...``. A full disk (family 10's
``No space left on device`` without a path) needs a tmpfs mount: ``tests/test_full_disk.py``.

Seeded (``--seed``): the kill moments and the random out-of-range values. About 200 runs. Measured:
202 runs in 541 s (9 min) on a quiet 2-core AMD EPYC with AVX512-BF16, 2026-12-07, families one after another
(docs/reliability.md, "Re-running the audit", has the counts)."""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import random
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# run as ``python tests/hostile_audit.py``: Python puts tests/ (the helpers it builds inputs with) first on sys.path

#: Environment variables the commands read that a hostile case sets; removed from every run's base environment.
PROJECT_ENV = ("DETECTOR_GEMM", "WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT",
               "DETECTOR_JOIN_TIMEOUT_S", "TORCHELASTIC_USE_AGENT_STORE", "MPCHAIR_EMBREE_ISA")
#: Names of what a run must not leave behind: atomic temp files, hidden work / old folders, lock files.
LEFTOVER = re.compile(r"^\..+\.tmp$|^\..+\.work|^\..+\.old\d*|\.lock$")


@dataclasses.dataclass(frozen=True)
class Run:
    """One command line run and its verdicts (``failures`` empty: it held)."""

    family: str
    name: str
    command: tuple[str, ...]
    env: dict[str, str]
    exit_code: int | None
    seconds: float
    failures: tuple[str, ...]
    stderr_tail: str


@dataclasses.dataclass(frozen=True)
class Outcome:
    """What a process did: exit code (negative: killed by that signal), seconds, stdout, stderr, peak RSS, hang."""

    code: int | None
    seconds: float
    stdout: str
    stderr: str
    max_rss_kib: int
    hung: bool
    orphans: tuple[int, ...] = ()


@dataclasses.dataclass
class Audit:
    """The run's settings, its shared inputs (built once, lazily) and the runs so far."""

    base: Path
    bin: Path
    timeout: float
    max_rss_gib: float
    seed: int
    limit: int | None
    runs: list[Run] = dataclasses.field(default_factory=list)
    cache: dict[str, object] = dataclasses.field(default_factory=dict)
    counter: int = 0

    def shared(self, key: str, build: Callable[[Path], object]) -> object:
        """The shared input ``key``, built into ``base/shared/key`` the first time it is asked for."""
        if key not in self.cache:
            self.cache[key] = build(self.base / "shared" / key)
        return self.cache[key]


class Enough(Exception):
    """The family's ``--limit`` of runs is reached."""


# --- processes -----------------------------------------------------------------------------------------------------


def _proc_stat(pid: int) -> tuple[str, int, int] | None:
    """(state, ppid, process group) of ``pid``, None when it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    except (FileNotFoundError, ProcessLookupError, PermissionError):
        return None
    return fields[0], int(fields[1]), int(fields[2])


def group_members(pgid: int) -> list[int]:
    """Live (not zombie) processes of process group ``pgid``."""
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            st = _proc_stat(int(entry.name))
            if st and st[2] == pgid and st[0] not in ("Z", "X"):
                out.append(int(entry.name))
    return out


def children(pid: int) -> list[int]:
    """Child processes of ``pid`` (its main thread's)."""
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except (FileNotFoundError, ProcessLookupError):
        return []


def _ended(pids: list[int], within: float) -> list[int]:
    """Those of ``pids`` still alive (not zombies) after ``within`` seconds."""
    deadline = time.monotonic() + within
    while True:
        alive = [p for p in pids if (st := _proc_stat(p)) and st[0] not in ("Z", "X")]
        if not alive or time.monotonic() > deadline:
            return alive
        time.sleep(0.1)


def _kill_all(pids: list[int]) -> None:
    for p in pids:
        try:
            os.kill(p, signal.SIGKILL)
        except ProcessLookupError:
            pass


def start(argv: list[str], cwd: Path, env: dict[str, str]) -> tuple[subprocess.Popen, Path]:
    """Start ``argv`` in its own process group with stdout / stderr to files in a scratch folder."""
    scratch = Path(tempfile.mkdtemp(prefix="io-", dir=cwd.parent))
    with open(scratch / "out", "wb") as out, open(scratch / "err", "wb") as err:
        proc = subprocess.Popen(argv, cwd=cwd, env=env, stdin=subprocess.DEVNULL, stdout=out, stderr=err,
                                start_new_session=True)
    return proc, scratch


def finish(proc: subprocess.Popen, scratch: Path, t0: float, timeout: float,
           on_tick: Callable[[], bool] | None = None) -> Outcome:
    """Wait for ``proc`` (at most ``timeout`` s; ``on_tick`` is called while it runs and ends the wait when it
    returns True), kill its group if it hangs, and read what it printed."""
    hung = False
    usage = None
    status = 0
    try:
        while True:
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                proc.returncode = os.waitstatus_to_exitcode(status)
                break
            if on_tick is not None and on_tick():
                on_tick = None
            if time.monotonic() - t0 > timeout:
                hung = True
                _kill_all(group_members(proc.pid) or [proc.pid])
                _, status, usage = os.wait4(proc.pid, 0)
                proc.returncode = os.waitstatus_to_exitcode(status)
                break
            time.sleep(0.05)
    except BaseException:  # the audit stopped (Ctrl-C, SIGTERM): leave no process of its own behind
        _kill_all(group_members(proc.pid) or [proc.pid])
        raise
    seconds = time.monotonic() - t0
    out = (scratch / "out").read_text(errors="replace")
    err = (scratch / "err").read_text(errors="replace")
    shutil.rmtree(scratch)
    return Outcome(None if hung else proc.returncode, seconds, out, err, usage.ru_maxrss if usage else 0, hung)


def base_env() -> dict[str, str]:
    """The environment every run starts from: the project's code first on the path, a headless plotting backend,
    and none of the variables a hostile case sets."""
    env = {k: v for k, v in os.environ.items() if k not in PROJECT_ENV}
    env.update(PYTHONPATH=str(ROOT), MPLBACKEND="Agg", PYVISTA_OFF_SCREEN="true", PYTHONUNBUFFERED="1")
    return env


# --- folders -------------------------------------------------------------------------------------------------------


def snapshot(folder: Path) -> dict[str, str]:
    """Every entry under ``folder``: relative path -> sha256 of a file, ``link:TARGET``, ``dir`` or ``special``."""
    out: dict[str, str] = {}
    if not folder.exists():
        return out
    for dirpath, dirnames, filenames in os.walk(folder):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            rel = str(p.relative_to(folder))
            if p.is_symlink():
                out[rel] = f"link:{os.readlink(p)}"
            elif p.is_dir():
                out[rel] = "dir"
            elif p.is_file():
                out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
            else:
                out[rel] = "special"
        dirnames[:] = [d for d in dirnames if not (Path(dirpath) / d).is_symlink()]
    return out


def leftovers(folder: Path) -> list[str]:
    """Temp files, hidden work / old folders and lock files under ``folder``."""
    return sorted(rel for rel in snapshot(folder) if LEFTOVER.search(Path(rel).name))


def one_line(stderr: str) -> list[str]:
    """The stderr lines that count for the one-line rule (``warning:`` lines and blank lines aside)."""
    return [ln for ln in stderr.splitlines() if ln.strip() and not ln.startswith("warning:")]


# --- one run -------------------------------------------------------------------------------------------------------


def case_dir(audit: Audit, family: str, name: str) -> Path:
    """A new empty folder for one run."""
    audit.counter += 1
    slug = re.sub(r"[^A-Za-z0-9]+", "-", name).strip("-")[:40]
    folder = audit.base / family / f"{audit.counter:03d}-{slug}"
    folder.mkdir(parents=True)
    return folder


def record(audit: Audit, family: str, name: str, argv: list[str], env: dict[str, str], outcome: Outcome,
           failures: list[str]) -> Run:
    """Add a run to the audit (and stop the family at its ``--limit``)."""
    if outcome.max_rss_kib > audit.max_rss_gib * 2**20:
        failures.append("memory")
    run = Run(family, name, tuple(argv), {k: v for k, v in env.items() if k in PROJECT_ENV or k == "MPLBACKEND"},
              outcome.code, round(outcome.seconds, 2), tuple(dict.fromkeys(failures)), outcome.stderr[-600:])
    audit.runs.append(run)
    mark = "ok" if not run.failures else "FAIL " + ",".join(run.failures)
    print(f"  {family}: {name}: exit {run.exit_code} in {run.seconds:.1f} s: {mark}", file=sys.stderr, flush=True)
    if audit.limit is not None and sum(r.family == family for r in audit.runs) >= audit.limit:
        raise Enough
    return run


def execute(audit: Audit, argv: list[str], cwd: Path, env: dict[str, str], timeout: float | None = None) -> Outcome:
    """Run ``argv`` to its end; an apparent hang is run once more with 5 x the time before it counts as one."""
    timeout = timeout or audit.timeout
    proc, scratch = start(argv, cwd, env)
    outcome = finish(proc, scratch, time.monotonic(), timeout)
    if outcome.hung:
        proc, scratch = start(argv, cwd, env)
        outcome = finish(proc, scratch, time.monotonic(), 5 * timeout)
    left = _ended(group_members(proc.pid), 10.0)  # workers die with PR_SET_PDEATHSIG: give them a moment
    _kill_all(left)
    return dataclasses.replace(outcome, orphans=tuple(left))


def check(audit: Audit, family: str, name: str, argv: list[str], *, expect: str = "refuse", needle: str = "",
          env: dict[str, str] | None = None, cwd: str = "", user: tuple[str, ...] = (),
          setup: Callable[[Path], None] | None = None, timeout: float | None = None) -> Run:
    """Run one command line in a fresh folder (``setup`` fills it first; ``{dir}`` in ``argv`` is that folder; the
    run's current folder is ``cwd`` inside it) and check it. ``expect``: ``refuse`` (exit 1 / 2, one ``error:``
    line holding ``needle``, the folder as it was), ``ok`` (exit 0, ``needle`` in stdout + stderr, no leftovers,
    the ``user`` paths as they were) or ``warn`` (``ok`` with a ``warning:`` line holding ``needle``)."""
    folder = case_dir(audit, family, name)
    if setup is not None:
        setup(folder)
    argv = [a.replace("{dir}", str(folder)) for a in argv]
    env = {**base_env(), **(env or {})}
    before = snapshot(folder)
    outcome = execute(audit, argv, folder / cwd, env, timeout)
    after = snapshot(folder)
    failures = _verdicts(outcome, expect, needle)
    if expect == "refuse":
        changed = [k for k in before if after.get(k) != before[k]]
        if changed:
            failures.append("deleted")
        if set(after) - set(before):
            failures.append("partial")
    else:
        if any(after.get(k) != v for k, v in before.items() if any(k == u or k.startswith(u + "/") for u in user)):
            failures.append("deleted")
        if leftovers(folder):
            failures.append("partial")
    return record(audit, family, name, argv, env, outcome, failures)


def _verdicts(outcome: Outcome, expect: str, needle: str) -> list[str]:
    failures = ["orphan"] if outcome.orphans else []
    if outcome.hung:
        return [*failures, "hang"]
    if "Traceback" in outcome.stderr:
        failures.append("traceback")
    if expect == "refuse":
        if outcome.code == 0:
            failures.append("accepted")
        elif outcome.code not in (1, 2):
            failures.append("crash")
        lines = one_line(outcome.stderr)
        if len(lines) != 1 or not lines[0].startswith("error: "):
            failures.append("multiline")
        elif needle and needle not in lines[0]:
            failures.append("message")
    else:
        if outcome.code != 0:
            failures.append("failed")
        elif needle and expect == "warn" and not any(
                ln.startswith("warning:") and needle in ln for ln in outcome.stderr.splitlines()):
            failures.append("accepted")
        elif needle and expect == "ok" and needle not in outcome.stdout + outcome.stderr:
            failures.append("message")
    return failures


# --- shared inputs (the tests' builders) -----------------------------------------------------------------------------


def slim_config(audit: Audit) -> Path:
    """The tests' slim experiment config (2 epochs of 4 samples, a checkpoint every epoch, no evaluation)."""
    from helpers_detector import write_test_config

    def build(folder: Path) -> Path:
        folder.mkdir(parents=True)
        return write_test_config(folder / "slim.yaml", train=dict(batch_size=2, epochs=2, samples_per_epoch=4))

    return audit.shared("config", build)


def dataset(audit: Audit) -> Path:
    """A 4-frame KITTI dataset of synthetic chairs (tests/helpers_detector.py)."""
    from helpers_detector import make_tiny_dataset

    return audit.shared("dataset", lambda folder: make_tiny_dataset(folder, n_frames=4, seed=audit.seed))


def checkpoint(audit: Audit, poison: bool = False) -> Path:
    """Random weights of the slim model (seeded), all NaN when ``poison``."""

    def build(folder: Path) -> Path:
        import torch

        from detector.checkpoint import Checkpoint, save_checkpoint
        from detector.config import load_experiment
        from detector.models import build_model

        torch.manual_seed(audit.seed)
        state = build_model(load_experiment(slim_config(audit)).model).state_dict()
        if poison:
            state = {k: v.float().fill_(float("nan")) if v.is_floating_point() else v for k, v in state.items()}
        folder.mkdir(parents=True)
        save_checkpoint(folder / "w.pt", Checkpoint(model=state))
        return folder / "w.pt"

    return audit.shared("nan-checkpoint" if poison else "checkpoint", build)


def stream_folder(audit: Audit, rate: object = 10.0, bad_point: float | None = None, deep: bool = False) -> Path:
    """The tests' two-frame stream (tests/helpers_recordings.py) with ``rate_hz`` = ``rate``, a scan point set to
    ``bad_point``, or a ``stream.json`` nested 100,000 deep."""
    from helpers_recordings import small_stream

    def build(folder: Path) -> Path:
        import numpy as np

        small_stream(folder, rate)
        if bad_point is not None:
            scan = folder / "sequences/00/velodyne/000001.bin"
            pts = np.fromfile(scan, dtype="<f4").reshape(-1, 4)
            pts[3, 1] = bad_point
            pts.tofile(scan)
        if deep:
            (folder / "stream.json").write_text('{"sequences": ' + "[" * 100_000 + "]" * 100_000 + "}")
        return folder

    return audit.shared(f"stream-{rate}-{bad_point}-{deep}", build)


def stream_readers(audit: Audit, data: Path) -> list[tuple[str, list[str]]]:
    """The three commands that read a stream's ``stream.json`` (``view --mcap``, ``view --rerun``, ``stream-eval
    --oracle``), named, on stream folder ``data``."""
    return [("view --mcap", mp(audit, "view", data, "--mcap", "{dir}/o.mcap")),
            ("view --rerun", mp(audit, "view", data, "--rerun", "{dir}/o.rrd")),
            ("stream-eval", det(audit, "stream-eval", "--data", data, "--oracle", "--latency-ms", 0, "--quiet"))]


def houses(audit: Audit) -> tuple[Path, str]:
    """One clean synthetic house made by ``mpchair synth`` (a run of the audit itself): (root, house id)."""

    def build(folder: Path) -> tuple[Path, str]:
        argv = [str(audit.bin / "mpchair"), "synth", "--out", str(folder), "--houses", "1", "--seed", "7",
                "--realism", "clean", "--json"]
        folder.parent.mkdir(parents=True, exist_ok=True)
        outcome = execute(audit, argv, folder.parent, base_env(), 10 * audit.timeout)
        if outcome.code != 0:
            raise SystemExit(f"error: mpchair synth failed: {outcome.stderr.strip()[-300:]}")
        return folder, json.loads(outcome.stdout)["houses"][0]

    return audit.shared("houses", build)


def user_folder(path: Path, **extra: str) -> None:
    """A folder a user owns: a thesis, its git folder, raw measurements (tests/test_owned_outputs.py's)."""
    files = {"thesis.tex": "\\documentclass{article}\n", ".git/HEAD": "ref: refs/heads/main\n",
             "raw/measurements.csv": "t,x\n0,1\n", **extra}
    for rel, text in files.items():
        (path / rel).parent.mkdir(parents=True, exist_ok=True)
        (path / rel).write_text(text)


def free_port() -> int:
    """A TCP port nobody listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# --- the families --------------------------------------------------------------------------------------------------


def mp(audit: Audit, *args: object) -> list[str]:
    return [str(audit.bin / "mpchair"), *map(str, args)]


def det(audit: Audit, *args: object) -> list[str]:
    return [str(audit.bin / "detector"), *map(str, args)]


def repro(audit: Audit, *args: object) -> list[str]:
    return [str(audit.bin / "python"), str(ROOT / "tools" / "reproduce.py"), *map(str, args)]


def kill_main_alone(audit: Audit, family: str, name: str, argv: list[str], out: Path, ready: Callable[[], bool],
                    rng: random.Random, resume: list[str] | None = None) -> None:
    """Start ``argv``, wait for ``ready()`` (and a seeded moment more), SIGKILL the main process alone (the
    out-of-memory killer's choice), check its children end, then run ``resume`` (default: the same command) and
    check it succeeds and leaves no temp or lock file."""
    env = base_env()
    folder = out.parent
    proc, scratch = start(argv, folder, env)
    t0 = time.monotonic()
    kids: list[int] = []
    delay = rng.uniform(0.0, 1.5)
    state = {"ready_at": None}

    def tick() -> bool:
        nonlocal kids
        if state["ready_at"] is None and ready():
            state["ready_at"] = time.monotonic()
        if state["ready_at"] is not None and time.monotonic() - state["ready_at"] >= delay:
            kids = children(proc.pid)
            os.kill(proc.pid, signal.SIGKILL)
            return True
        return False

    outcome = finish(proc, scratch, t0, 10 * audit.timeout, tick)
    failures = []
    alive = _ended(kids + group_members(proc.pid), 10.0)
    if alive:
        failures.append("orphan")
        _kill_all(alive)
    if outcome.hung:
        failures.append("hang")
    if "Traceback" in outcome.stderr:
        failures.append("traceback")
    killed = outcome.code == -signal.SIGKILL
    record(audit, family, f"{name}: SIGKILL to the main process"
           f"{'' if killed else ' (it ended first)'}", argv, env, outcome, failures)
    check_resume(audit, family, f"{name}: the same command after the kill", resume or argv, folder)


def check_resume(audit: Audit, family: str, name: str, argv: list[str], folder: Path) -> Outcome:
    """Run ``argv`` in ``folder`` (which holds a killed run's output) and check it succeeds and leaves nothing."""
    env = base_env()
    outcome = execute(audit, argv, folder, env, 10 * audit.timeout)
    failures = _verdicts(outcome, "ok", "")
    if leftovers(folder):
        failures.append("partial")
    record(audit, family, name, argv, env, outcome, failures)
    return outcome


def family_orphans(audit: Audit, rng: random.Random) -> None:
    """Item 1: SIGKILL of the main process alone of ``generate --workers 2`` / ``stream --workers 2``."""
    root, house = houses(audit)
    for i in range(2):
        folder = case_dir(audit, "orphans", f"generate {i}")
        out = folder / "out"
        argv = mp(audit, "generate", "--root", root, "--house", house, "--frames", 8, "--out", out, "--seed", i,
                  "--workers", 2, "--quiet")
        kill_main_alone(audit, "orphans", f"generate --workers 2 (#{i})", argv, out,
                        lambda out=out: any((out / ".frames").glob("*.json")), rng)
    folder = case_dir(audit, "orphans", "stream")
    out = folder / "out"
    argv = mp(audit, "stream", "--root", root, "--house", house, "--episodes", 1, "--rate", 1, "--duration", 6,
              "--no-look-around", "--seed", 4, "--out", out, "--quiet", "--workers", 2)
    kill_main_alone(audit, "orphans", "stream --workers 2", argv, out,
                    lambda: any((out / ".frames").rglob("*.json")), rng)


def family_user_files(audit: Audit, rng: random.Random) -> None:
    """Item 2: commands that replaced folders the user owns."""
    fam = "user-files"
    cfg, data, ckpt = slim_config(audit), dataset(audit), checkpoint(audit)

    def work_and_thesis(d: Path) -> None:
        for rel, text in {"w/commands.log": "log\n", "w/results/weights.json": "{}"}.items():
            (d / rel).parent.mkdir(parents=True, exist_ok=True)
            (d / rel).write_text(text)
        user_folder(d / "thesis")

    rec = ["--scale", "small", "--steps", "record", "--out", "{dir}/w"]
    check(audit, fam, "reproduce --record THESIS", repro(audit, *rec, "--record", "{dir}/thesis"),
          needle="will not replace this folder", setup=work_and_thesis)
    check(audit, fam, "reproduce --record . (the work folder)", repro(audit, *rec, "--record", "."),
          needle="is the current folder", setup=work_and_thesis, cwd="w")
    check(audit, fam, "reproduce --record .. (holds the current folder)", repro(audit, *rec, "--record", ".."),
          needle="current folder", setup=work_and_thesis, cwd="w")

    check(audit, fam, "reproduce --record NEW", repro(audit, *rec, "--record", "{dir}/rec"), expect="ok",
          setup=work_and_thesis, user=("thesis", "w"))

    exp = ["export", "--config", cfg, "--format", "onnx", "--seed", 0]
    check(audit, fam, "export --out over a user folder with deploy.json",
          det(audit, *exp, "--out", "{dir}/project"), needle="will not replace this folder",
          setup=lambda d: user_folder(d / "project", **{"deploy.json": "{}", "main.c": "int main(){}\n"}))
    check(audit, fam, "export --out NEW", det(audit, *exp, "--out", "{dir}/exported"), expect="ok", needle="wrote")
    own = audit.base / fam / "own-export"
    if not own.exists():
        outcome = execute(audit, det(audit, *exp, "--out", own), audit.base, base_env())
        if outcome.code != 0:
            raise SystemExit(f"error: a plain export failed: {outcome.stderr.strip()[-300:]}")

    def export_plus_user_file(d: Path) -> None:
        shutil.copytree(own, d / "exported")
        (d / "exported/main.c").write_text("int main(){}\n")

    check(audit, fam, "export --out an older export a file was added to", det(audit, *exp, "--out", "{dir}/exported"),
          needle="it holds main.c", setup=export_plus_user_file)

    def symlinked_export(d: Path) -> None:
        shutil.copytree(own, d / "exported")
        (d / "link").symlink_to(d / "exported", target_is_directory=True)
        user_folder(d / "mine")

    check(audit, fam, "export --out a symlink to its own export", det(audit, *exp, "--out", "{dir}/link"),
          expect="ok", needle="wrote", setup=symlinked_export, user=("mine", "link"))
    ev = ["eval", "--config", cfg, "--data", data, "--checkpoint", ckpt, "--threads", 1]
    check(audit, fam, "eval --out DIR with a user's DIR/data/raw", det(audit, *ev, "--out", "{dir}/ev"),
          needle="will not replace this folder", setup=lambda d: user_folder(d / "ev/data"))
    check(audit, fam, "eval --out DIR with user files beside data/", det(audit, *ev, "--out", "{dir}/ev"),
          expect="ok", setup=lambda d: user_folder(d / "ev"), user=("ev/thesis.tex", "ev/.git", "ev/raw"))
    tr = ["train", "--config", cfg, "--data", data, "--threads", 1, "--no-progress"]
    check(audit, fam, "train --out a folder that is not a run", det(audit, *tr, "--out", "{dir}/project"),
          needle="is not a training run",
          setup=lambda d: user_folder(d / "project", **{"config.yaml": "mine: 1\n", ".notes.tmp": "draft"}))
    check(audit, fam, "train --out a folder holding only a user's .x.tmp", det(audit, *tr, "--out", "{dir}/project"),
          needle="is not a training run", setup=lambda d: user_folder(d / "project", **{"sub/.draft.tmp": "x"}))


def sensor_yaml(folder: Path, profile: str, old: str, new: str) -> Path:
    """A copy of a shipped sensor profile with one line edited."""
    text = (ROOT / "mpchair/scan/profiles" / f"{profile}.yaml").read_text()
    if old not in text:
        raise SystemExit(f"error: {profile}.yaml no longer holds {old!r}: update tests/hostile_audit.py")
    path = folder / "s.yaml"
    path.write_text(text.replace(old, new))
    return path


def status_work(folder: Path, config: str, metrics: str | None, special: str = "") -> None:
    """A work folder with one run (``runs/dense``) for ``reproduce.py --status``; ``special`` puts a FIFO, a link to
    /dev/zero or a folder in place of its ``metrics.jsonl``."""
    run = folder / "w/runs/dense"
    run.mkdir(parents=True)
    (run / "config.yaml").write_text(config)
    m = run / "metrics.jsonl"
    if special == "fifo":
        os.mkfifo(m)
    elif special == "devzero":
        m.symlink_to("/dev/zero")
    elif special == "dir":
        m.mkdir()
    elif metrics is not None:
        m.write_text(metrics)


def run_config_text(audit: Audit) -> str:
    """A whole ``RUN/config.yaml`` as ``detector train`` writes it."""
    from helpers_detector import write_run_config

    return audit.shared("run-config", lambda f: write_run_config(
        f, train=dict(epochs=2, batch_size=2, samples_per_epoch=4)).read_text())


STEP = '{"kind": "step", "step": 1, "epoch": 0, "time_s": 0.5}\n'


def family_hangs(audit: Audit, rng: random.Random) -> None:
    """Item 4: special files under ``--status``, sensors too large, a lone rank, unbounded ``--workers``."""
    fam = "hangs"
    good = run_config_text(audit)
    for special in ("fifo", "devzero", "dir"):
        check(audit, fam, f"reproduce --status, metrics.jsonl a {special}",
              repro(audit, "--status", "--out", "{dir}/w"), needle="runs/dense",
              setup=lambda d, s=special: status_work(d, good, None, s))
    check(audit, fam, "reproduce --status, config.yaml a FIFO", repro(audit, "--status", "--out", "{dir}/w"),
          needle="config.yaml", setup=lambda d: (status_work(d, good, STEP), (d / "w/runs/dense/config.yaml").unlink(),
                                                 os.mkfifo(d / "w/runs/dense/config.yaml")))
    root, house = houses(audit)
    gen = ["generate", "--root", root, "--house", house, "--frames", 1, "--out", "{dir}/out", "--quiet"]
    for profile, old, new in (("lidar16", "beams: 16", "beams: 100000"), ("lidar16", "beams: 16", "beams: 100000000"),
                              ("lidar16", "columns: 1800", "columns: 1e9"),
                              ("lidar16", "width: 1024", "width: 10000000"),
                              ("lidar16", "height: 1024", "height: 10000000"),
                              ("lidar16", "columns: 1800", f"columns: {rng.randrange(10**8, 10**10)}")):
        check(audit, fam, f"generate --sensor {profile} {new}", mp(audit, *gen, "--sensor", "{dir}/s.yaml"),
              needle="s.yaml", setup=lambda d, p=profile, o=old, n=new: sensor_yaml(d, p, o, n))
    port = free_port()
    tr = ["train", "--config", slim_config(audit), "--data", dataset(audit), "--out", "{dir}/run", "--threads", 1,
          "--no-progress"]
    check(audit, fam, "a lone rank WORLD_SIZE=2 RANK=0 (MASTER_* set)", det(audit, *tr),
          needle="the other ranks did not join",
          env=dict(WORLD_SIZE="2", RANK="0", LOCAL_RANK="0", MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port),
                   DETECTOR_JOIN_TIMEOUT_S="5"))
    check(audit, fam, "WORLD_SIZE=2 RANK=0 without torchrun", det(audit, *tr), needle="torchrun",
          env=dict(WORLD_SIZE="2", RANK="0"))
    for n in (100_000, 10**9, 2**63, rng.randrange(10**4, 10**6)):
        check(audit, fam, f"generate --workers {n}", mp(audit, *gen, "--workers", n), needle="--workers")
    check(audit, fam, "stream --workers 100000", mp(audit, "stream", "--root", root, "--house", house, "--out",
                                                    "{dir}/o", "--workers", 100_000), needle="--workers")
    check(audit, fam, "reproduce --workers 100000", repro(audit, "--scale", "small", "--out", "{dir}/w", "--dry-run",
                                                          "--workers", 100_000), needle="--workers")


def family_threads(audit: Audit, rng: random.Random) -> None:
    """Item 5: ``--threads`` past the machine (a segfault, exit 139, before)."""
    cfg, data, ckpt = slim_config(audit), dataset(audit), checkpoint(audit)
    commands = {
        "eval": ["eval", "--config", cfg, "--data", data, "--checkpoint", ckpt, "--out", "{dir}/ev"],
        "stream-eval": ["stream-eval", "--data", stream_folder(audit), "--oracle", "--latency-ms", "0", "--quiet"],
        "bench": ["bench", "--config", cfg, "--frames", 1, "--trials", 1],
        "train": ["train", "--config", cfg, "--data", data, "--out", "{dir}/run", "--no-progress"],
    }
    for value in (100_000, 2**31, 2**64, -1, rng.randrange(10**3, 10**7)):
        for name, args in commands.items():
            check(audit, "threads", f"{name} --threads {value}", det(audit, *args, "--threads", value),
                  needle="--threads")
    for value in (100_000, 0):
        check(audit, "threads", f"reproduce --threads {value}", repro(audit, "--scale", "small", "--out", "{dir}/w",
                                                                       "--dry-run", "--threads", value),
              needle="--threads")


def edited_record(folder: Path, meta: dict, files: dict[str, bytes] | None = None) -> None:
    """A run record ``folder/rec`` (record.json from ``meta`` over a valid small-scale one, its files)."""
    from reproduction.scales import SCALES

    rec = folder / "rec"
    files = {"results/a.json": b"{}"} if files is None else files
    for rel, data in files.items():
        (rec / rel).parent.mkdir(parents=True, exist_ok=True)
        (rec / rel).write_bytes(data)
    sizes = dataclasses.asdict(SCALES["small"])
    base = {"scale": "small", "notes": [], "dataset_sha256": None, "files": sorted(files)}
    full = {**base, **meta, "scale_sizes": {**sizes, **meta.get("scale_sizes", {})}}
    (rec / "record.json").write_text(json.dumps(full))


def family_tracebacks(audit: Audit, rng: random.Random) -> None:
    """Item 6: each of these ended in a traceback."""
    fam = "tracebacks"
    cfg, data, ckpt = slim_config(audit), dataset(audit), checkpoint(audit)
    root, house = houses(audit)
    big = rng.randrange(2**64, 2**80)
    for name, argv in (
            ("synth --seed 2^64", mp(audit, "synth", "--out", "{dir}/o", "--seed", 2**64)),
            (f"synth --seed {big}", mp(audit, "synth", "--out", "{dir}/o", "--seed", big)),
            ("generate --seed 2^70", mp(audit, "generate", "--root", root, "--house", house, "--frames", 1, "--out",
                                        "{dir}/o", "--seed", 2**70)),
            ("export --seed 2^64", det(audit, "export", "--config", cfg, "--format", "onnx", "--out", "{dir}/o",
                                       "--seed", 2**64)),
            ("bench --seed -1", det(audit, "bench", "--config", cfg, "--seed", -1)),
            ("reproduce --seed 2^70", repro(audit, "--scale", "small", "--out", "{dir}/w", "--dry-run", "--seed",
                                            2**70))):
        check(audit, fam, name, argv, needle="--seed")
    for rate in ("nan", "inf", "-inf", "1e-300", "0", "-5"):
        check(audit, fam, f"bench --rate {rate}", det(audit, "bench", "--config", cfg, "--rate", rate),
              needle="--rate")
    for dur in ("nan", "inf", "-1"):
        check(audit, fam, f"bench --duration {dur}", det(audit, "bench", "--config", cfg, "--rate", 10, "--duration",
                                                          dur), needle="--duration")
    detector_cmds = {
        "train": ["train", "--config", cfg, "--data", data, "--out", "{dir}/run", "--threads", 1, "--no-progress"],
        "eval": ["eval", "--config", cfg, "--data", data, "--checkpoint", ckpt, "--out", "{dir}/ev", "--threads", 1],
        "export": ["export", "--config", cfg, "--format", "onnx", "--out", "{dir}/o"],
        "bench": ["bench", "--config", cfg, "--frames", 1, "--trials", 1, "--threads", 1],
        "stream-eval": ["stream-eval", "--data", stream_folder(audit), "--oracle", "--latency-ms", "0", "--quiet"],
    }
    envs = [({"DETECTOR_GEMM": "bogus"}, "DETECTOR_GEMM"), ({"WORLD_SIZE": "abc"}, "WORLD_SIZE"),
            ({"RANK": "abc"}, "RANK"), ({"LOCAL_RANK": "abc"}, "LOCAL_RANK"), ({"WORLD_SIZE": "2"}, "torchrun"),
            ({"WORLD_SIZE": "-3"}, "WORLD_SIZE")]
    for env, needle in envs:
        for name, args in detector_cmds.items():
            check(audit, fam, f"{' '.join(f'{k}={v}' for k, v in env.items())} detector {name}", det(audit, *args),
                  needle=needle, env=env)
    for env, needle in envs[:3]:
        check(audit, fam, f"{' '.join(f'{k}={v}' for k, v in env.items())} mpchair houses",
              mp(audit, "houses", "--root", root), needle=needle, env=env)
    view = mp(audit, "view", stream_folder(audit), "--sequence", "00", "--frame", 1, "--out", "{dir}/f.png")
    check(audit, fam, "MPLBACKEND=bogus mpchair view", view, needle="MPLBACKEND", env={"MPLBACKEND": "bogus"})
    check(audit, fam, "MPLBACKEND=bogus detector viz-sparsity", det(audit, "viz-sparsity", "--config", cfg, "--data",
                                                                     data, "--out", "{dir}/v.png"),
          needle="MPLBACKEND", env={"MPLBACKEND": "bogus"})

    fr = ["--steps", "report", "--out", "{dir}/w", "--from-record", "{dir}/rec"]
    records = [
        ("record.json nested 100,000 deep", None, "nested deeper than"),
        ("files entry ''", {"files": [""]}, "files"),
        ("files entry 123", {"files": [123]}, "files"),
        ("unknown scale_sizes key", {"scale_sizes": {"gigantic": 1}}, "scale_sizes"),
        ("notes: 5", {"notes": 5}, "notes"),
    ]
    for name, meta, needle in records:
        def setup(d: Path, meta=meta) -> None:
            if meta is None:
                (d / "rec").mkdir()
                (d / "rec/record.json").write_text("[" * 100_000 + "]" * 100_000)
            else:
                edited_record(d, meta)
        check(audit, fam, f"--from-record: {name}", repro(audit, *fr), needle=needle, setup=setup)
    for name, content in (("malformed", b'{"a": '), ("non-UTF-8", b"\xff\xfe{}"), ("deep", b"[" * 100_000)):
        check(audit, fam, f"--from-record: a {name} results JSON", repro(audit, *fr), needle="metrics.json",
              setup=lambda d, c=content: edited_record(d, {}, {"results/eval_dense/metrics.json": c}))

    def linked_results(d: Path) -> None:
        edited_record(d, {}, {"results/eval_dense/metrics.json": b"{}"})
        target = d / "outside.json"
        target.write_text("{}")
        (d / "rec/results/eval_dense/metrics.json").unlink()
        (d / "rec/results/eval_dense/metrics.json").symlink_to(target)

    check(audit, fam, "--from-record: a symlinked results JSON", repro(audit, *fr), needle="symbolic link",
          setup=linked_results)
    st = repro(audit, "--status", "--out", "{dir}/w")
    for name, config in (("bad YAML", "train: [1, 2\n"), ("batch_size: 0", good_replace(audit, "batch_size: 2",
                                                                                         "batch_size: 0")),
                         ("a list", "[1, 2]\n"), ("lr: nan", good_replace(audit, "batch_size: 2", "lr: .nan"))):
        check(audit, fam, f"--status, config.yaml {name}", st, needle="runs/dense",
              setup=lambda d, c=config: status_work(d, c, STEP))
    odd = '[1]\n{"kind": "step"}\n{"kind": "step", "step": "x", "time_s": 1}\n' + "[" * 5000 + "\n\xff\n" + STEP
    check(audit, fam, "--status, odd metrics.jsonl lines", st, expect="ok", needle="step 1",
          setup=lambda d: status_work(d, run_config_text(audit), odd))
    deep = stream_folder(audit, deep=True)
    for name, argv in stream_readers(audit, deep):
        check(audit, fam, f"{name} on a stream.json nested deep", argv, needle="nested deeper than")
    gen = ["generate", "--root", root, "--house", house, "--frames", 1, "--out", "{dir}/out", "--quiet"]
    for profile, old, new in (("mp3d-depth90", "row_step: 10", "row_step: 0"),
                              ("mp3d-depth90", "flat_step:", "flat_step: -1\nx_flat_step:")):
        check(audit, fam, f"generate --sensor {profile} {new.splitlines()[0]}",
              mp(audit, *gen, "--sensor", "{dir}/s.yaml"), needle="s.yaml",
              setup=lambda d, p=profile, o=old, n=new: sensor_yaml(d, p, o, n))


def good_replace(audit: Audit, old: str, new: str) -> str:
    """The whole run config with one line edited."""
    text = run_config_text(audit)
    if old not in text:
        raise SystemExit(f"error: the run config no longer holds {old!r}: update tests/hostile_audit.py")
    return text.replace(old, new, 1)


def family_bad_input(audit: Audit, rng: random.Random) -> None:
    """Item 7: bad input that was accepted."""
    fam = "bad-input"
    fr = ["--steps", "report", "--out", "{dir}/w", "--from-record", "{dir}/rec"]

    def evil_link(d: Path) -> None:
        edited_record(d, {}, {"results/a.json": b"{}", "results/evil.json": b"{}"})
        (d / "rec/results/evil.json").unlink()
        (d / "rec/results/evil.json").symlink_to("/etc/passwd")

    check(audit, fam, "--from-record: results/evil.json -> /etc/passwd", repro(audit, *fr), needle="symbolic link",
          setup=evil_link)
    for name, meta, needle in (
            ("dataset_sha256 null with a dataset", {"dataset_sha256": None}, "dataset_sha256"),
            ("scale gigantic", {"scale": "gigantic"}, "scale"),
            ("precision fp7", {"scale_sizes": {"precision": "fp7"}}, "precision"),
            ("epochs -3", {"scale_sizes": {"epochs": -3}}, "epochs"),
            ("houses 1e12", {"scale_sizes": {"houses": 10**12}}, "houses"),
            ("budget_seconds NaN", {"scale_sizes": {"budget_seconds": float("nan")}}, "budget_seconds"),
            ("notes 'hello'", {"notes": "hello"}, "notes"),
            ("dataset_sha256 'abc'", {"dataset_sha256": "abc"}, "dataset_sha256"),
            ("files outside the record", {"files": ["../outside.json"]}, "files"),
            ("files absolute", {"files": ["/etc/passwd"]}, "files")):
        files = {"results/a.json": b"{}", "dataset/manifest.json": b"{}"} if "with a dataset" in name else None

        def setup(d: Path, meta=meta, files=files) -> None:
            edited_record(d, meta, files)
            if "files" in meta:  # the listed files are the edit: keep them as written
                rec = json.loads((d / "rec/record.json").read_text())
                rec["files"] = meta["files"]
                (d / "rec/record.json").write_text(json.dumps(rec))
            (d / "outside.json").write_text("{}")

        check(audit, fam, f"--from-record: {name}", repro(audit, *fr), needle=needle, setup=setup)
    cfg = slim_config(audit)
    check(audit, fam, "export of all-NaN weights warns", det(audit, "export", "--config", cfg, "--checkpoint",
                                                               checkpoint(audit, poison=True), "--format", "onnx",
                                                               "--out", "{dir}/o"),
          expect="warn", needle="NaN")
    rates = [1e300, 0, float("nan"), -1, 1e-300, 1001, float("inf"), rng.uniform(1000.5, 1e6)]
    for rate in rates:
        data = stream_folder(audit, rate=rate)
        for name, argv in stream_readers(audit, data):
            check(audit, fam, f"{name} on rate_hz {rate:g}", argv, needle="rate_hz")
    for value in (float("nan"), float("inf")):
        data = stream_folder(audit, bad_point=value)
        for name, argv in (("view --mcap", mp(audit, "view", data, "--mcap", "{dir}/o.mcap")),
                           ("view --rerun", mp(audit, "view", data, "--rerun", "{dir}/o.rrd")),
                           ("view --out", mp(audit, "view", data, "--sequence", "00", "--frame", 1, "--out",
                                             "{dir}/f.png")),
                           # with a model (the committed weights): --oracle reads labels only, never a scan
                           ("stream-eval", det(audit, "stream-eval", "--data", data, "--config", "mpchair_dense_cpu",
                                               "--checkpoint", "pretrained:dense", "--latency-ms", 0, "--quiet"))):
            check(audit, fam, f"{name} on a {value} scan point", argv, needle="000001.bin")


def family_partial(audit: Audit, rng: random.Random) -> None:
    """Item 8: what killed runs left behind (exports, recordings), the next run's clean-up."""
    fam = "partial"
    cfg = slim_config(audit)
    for i in range(3):
        folder = case_dir(audit, fam, f"export killed {i}")
        out = folder / "o"
        argv = det(audit, "export", "--config", cfg, "--format", "onnx", "--seed", 0, "--out", out)
        outcome = execute(audit, argv, folder, base_env())  # an older export to replace
        if outcome.code != 0:
            raise SystemExit(f"error: a plain export failed: {outcome.stderr.strip()[-300:]}")
        old = snapshot(out)
        argv = det(audit, "export", "--config", cfg, "--format", "onnx", "--seed", 1, "--out", out)
        kill_main_alone(audit, fam, f"export #{i}", argv, out,
                        lambda folder=folder: any(p.name.startswith(".o.") for p in folder.iterdir()), rng)
        now = snapshot(out)
        if sorted(k for k in now if not k.startswith(".")) != sorted(k for k in old if not k.startswith(".")):
            record(audit, fam, f"export #{i}: OUT complete after the resumed export", [], {},
                   Outcome(0, 0.0, "", "", 0, False), ["mismatch"])
    stream = stream_folder(audit)
    for name, flag, ext in (("view --mcap", "--mcap", "mcap"), ("view --rerun", "--rerun", "rrd")):
        folder = case_dir(audit, fam, f"{name} killed")
        out = folder / f"x.{ext}"
        argv = mp(audit, "view", stream, flag, out)
        kill_main_alone(audit, fam, name, argv, out,
                        lambda folder=folder, ext=ext: any(p.name.endswith(".tmp") for p in folder.iterdir()), rng)


def family_resume(audit: Audit, rng: random.Random) -> None:
    """Item 9: a training killed past its first checkpoint resumes byte-identical (sha256) to an uninterrupted one."""
    fam = "resume"
    cfg, data = slim_config(audit), dataset(audit)
    args = ["train", "--config", cfg, "--data", data, "--threads", 1, "--no-progress", "--epochs", 3]
    ref = case_dir(audit, fam, "reference") / "run"
    env = base_env()
    argv = det(audit, *args, "--out", ref)
    outcome = execute(audit, argv, ref.parent, env, 10 * audit.timeout)
    record(audit, fam, "uninterrupted training", argv, env, outcome, _verdicts(outcome, "ok", ""))
    if outcome.code != 0:
        return
    want = {k: v for k, v in snapshot(ref).items() if k.endswith(".pt")}
    for i in range(3):
        run = case_dir(audit, fam, f"killed {i}") / "run"
        kill_main_alone(audit, fam, f"train #{i}", det(audit, *args, "--out", run), run,
                        lambda run=run: (run / "last.pt").is_file(), rng,
                        resume=det(audit, *args, "--out", run, "--resume"))
        got = {k: v for k, v in snapshot(run).items() if k.endswith(".pt")}
        record(audit, fam, f"train #{i}: checkpoints byte-identical after --resume", [], {},
               Outcome(0, 0.0, "", "", 0, False), [] if got == want else ["mismatch"])


def family_one_line(audit: Audit, rng: random.Random) -> None:
    """Item 10: errors that lacked a path or misled."""
    fam = "one-line"
    cfg, data = slim_config(audit), dataset(audit)
    from helpers_detector import write_test_config

    def diverging(d: Path) -> None:
        write_test_config(d / "lr.yaml", train=dict(batch_size=2, epochs=1, samples_per_epoch=4, lr=1e30))

    check(audit, fam, "train with lr 1e30 (no checkpoint yet)",
          det(audit, "train", "--config", "{dir}/lr.yaml", "--data", data, "--out", "{dir}/run", "--threads", 1,
              "--no-progress"), needle="no checkpoint was written yet", setup=diverging, timeout=10 * audit.timeout)
    check(audit, fam, "WORLD_SIZE=1 RANK=5", det(audit, "train", "--config", cfg, "--data", data, "--out",
                                                  "{dir}/run"), needle="RANK=5", env=dict(WORLD_SIZE="1", RANK="5"))

    def other_format(d: Path) -> None:
        import torch

        torch.save({"format": 999}, d / "x.pt")

    for name in ("eval", "export"):
        extra = (["eval", "--data", data, "--out", "{dir}/ev", "--threads", 1] if name == "eval" else
                 ["export", "--format", "onnx", "--out", "{dir}/o"])
        check(audit, fam, f"{name} of a format-999 checkpoint", det(audit, *extra, "--config", cfg, "--checkpoint",
                                                                    "{dir}/x.pt"),
              needle="checkpoint format 999", setup=other_format)
    view = stream_folder(audit, rate=1e300)
    check(audit, fam, "view --mcap rate_hz error names the file", mp(audit, "view", view, "--mcap", "{dir}/o.mcap"),
          needle=f"{view}/stream.json")
    hold = ("import sys; from mpchair.core.lock import folder_lock\n"
            "with folder_lock('.exp.export.lock', 'detector export', folder='exp'):\n"
            "    print('held', flush=True); sys.stdin.read()")
    folder = case_dir(audit, fam, "busy export")
    holder = subprocess.Popen([str(audit.bin / "python"), "-c", hold], cwd=folder, stdin=subprocess.PIPE,
                              stdout=subprocess.PIPE, text=True, env=base_env())
    try:
        if holder.stdout.readline() == "held\n":
            env = base_env()
            argv = det(audit, "export", "--config", cfg, "--format", "onnx", "--out", "exp")
            outcome = execute(audit, argv, folder, env)
            fails = _verdicts(outcome, "refuse", "error: exp: another detector export")
            if not outcome.stderr.startswith("error: exp: "):
                fails.append("message")
            if (folder / "exp").exists():
                fails.append("partial")
            record(audit, fam, "export on a busy folder names OUT", argv, env, outcome, fails)
    finally:
        holder.communicate("")
    for bad in ("--height nan", "--robot-radius inf", "--frames 0", "--frames -1", "--max-attempts 0"):
        root, house = houses(audit)
        check(audit, fam, f"generate {bad}", mp(audit, "generate", "--root", root, "--house", house, "--frames", 1,
                                                "--out", "{dir}/o", *bad.split()),
              needle=bad.split()[0])


#: Family name -> (issue item, function); the order is the issue's.
FAMILIES: dict[str, tuple[int, Callable[[Audit, random.Random], None] | None]] = {
    "orphans": (1, family_orphans),
    "user-files": (2, family_user_files),
    "export-2gib": (3, None),
    "hangs": (4, family_hangs),
    "threads": (5, family_threads),
    "tracebacks": (6, family_tracebacks),
    "bad-input": (7, family_bad_input),
    "partial": (8, family_partial),
    "resume": (9, family_resume),
    "one-line": (10, family_one_line),
}
SKIPPED = {"export-2gib": "skipped: an export over 2 GiB writes and verifies > 2 GiB (minutes of CPU); "
                          "tests/test_owned_outputs.py::test_an_export_whose_weights_lie_outside_... checks it"}


def run_families(audit: Audit, names: list[str]) -> Iterator[tuple[str, list[Run], float]]:
    """Run the named families in the issue's order: (name, its runs, seconds) for each."""
    for name in names:
        item, fn = FAMILIES[name]
        t0 = time.monotonic()
        first = len(audit.runs)
        if fn is not None:
            rng = random.Random(f"{audit.seed}:{name}")
            try:
                fn(audit, rng)
            except Enough:
                pass
        yield name, audit.runs[first:], time.monotonic() - t0


def summary_line(name: str, runs: list[Run], seconds: float) -> str:
    """``item name: runs, failed, kinds``."""
    if name in SKIPPED:
        return f"{FAMILIES[name][0]:>2} {name}: {SKIPPED[name]}"
    failed = [r for r in runs if r.failures]
    kinds: dict[str, int] = {}
    for r in failed:
        for k in r.failures:
            kinds[k] = kinds.get(k, 0) + 1
    what = ", ".join(f"{k} {n}" for k, n in sorted(kinds.items())) or "-"
    return f"{FAMILIES[name][0]:>2} {name}: {len(runs)} runs, {len(failed)} failed ({what}) in {seconds:.0f} s"


def main(argv: list[str] | None = None) -> int:
    """The command line: run the families, print one line each, exit 1 when a run failed."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                epilog="Families (issue 47's items): " + ", ".join(FAMILIES),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--family", action="append", choices=list(FAMILIES), default=None,
                   help="run this family only (repeat for several; default: all)")
    p.add_argument("--json", type=Path, default=None, metavar="PATH",
                   help="write every run (command, exit code, seconds, verdicts) as JSON")
    p.add_argument("--timeout", type=float, default=120.0,
                   help="seconds before a run counts as hung (it is re-run once with 5x this; runs that train or "
                        "generate get 10x) (default 120)")
    p.add_argument("--max-rss-gib", type=float, default=4.0, help="peak memory per run before it counts (default 4)")
    p.add_argument("--seed", type=int, default=0, help="seed of the kill moments and random values (default 0)")
    p.add_argument("--limit", type=int, default=None, help="at most this many runs per family (a quick check)")
    p.add_argument("--bin", type=Path, default=ROOT / ".venv" / "bin",
                   help="folder holding mpchair, detector and python (default: the clone's .venv/bin)")
    p.add_argument("--keep", action="store_true", help="keep the temporary work folder (its path is printed)")
    args = p.parse_args(argv)
    # SIGTERM ends the audit like Ctrl-C: the run under way is killed and --json still gets the runs so far
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    if not math.isfinite(args.timeout) or args.timeout <= 0:
        p.error("--timeout must be a positive number of seconds")
    for tool in ("mpchair", "detector", "python"):
        if not (args.bin / tool).exists():
            print(f"error: {args.bin / tool}: not found (give --bin the folder of the installed commands)",
                  file=sys.stderr)
            return 2
    names = [n for n in FAMILIES if args.family is None or n in args.family]
    base = Path(tempfile.mkdtemp(prefix="hostile-audit-"))
    audit = Audit(base=base, bin=args.bin.absolute(), timeout=args.timeout, max_rss_gib=args.max_rss_gib,
                  seed=args.seed, limit=args.limit)
    t0 = time.monotonic()
    families = {}
    try:
        for name, runs, seconds in run_families(audit, names):
            print(summary_line(name, runs, seconds), flush=True)
            families[name] = {"item": FAMILIES[name][0], "runs": len(runs),
                              "failed": sum(bool(r.failures) for r in runs), "seconds": round(seconds, 1),
                              "skipped": SKIPPED.get(name)}
    finally:
        total = time.monotonic() - t0
        for name in names:  # a family cut short (SIGTERM) counts its runs so far
            runs = [r for r in audit.runs if r.family == name]
            if name not in families and runs:
                families[name] = {"item": FAMILIES[name][0], "runs": len(runs),
                                  "failed": sum(bool(r.failures) for r in runs), "seconds": None,
                                  "skipped": "cut short"}
        if args.json is not None:
            from mpchair.core.atomic import write_text

            doc = {"seed": args.seed, "timeout_s": args.timeout, "seconds": round(total, 1), "families": families,
                   "runs": [dataclasses.asdict(r) for r in audit.runs]}
            write_text(args.json, json.dumps(doc, indent=1) + "\n")
        if args.keep:
            print(f"work folder kept: {base}", file=sys.stderr)
        else:
            shutil.rmtree(base, ignore_errors=True)
    failed = sum(bool(r.failures) for r in audit.runs)
    print(f"{len(audit.runs)} runs, {failed} failed, {total:.0f} s")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
