"""Faults, injected for real: SIGKILL at every file rename of a run, a pool worker killed with SIGKILL, a worker that
fails (file size limit), a full disk (tmpfs), two processes on one folder, a crafted checkpoint, a kill during the
end-of-epoch evaluation, bad settings and data. Each test asserts what is on disk and the exit status afterwards
(docs/reliability.md lists the cases and what each guarantees)."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers_detector import make_tiny_dataset, write_test_config
from helpers_faults import count_replaces, kill_at_replace, mounted_tmpfs, run_forked, tree

from detector.cli import main as detector_main
from detector.train import train
from mpchair.cli import main as mpchair_main
from mpchair.dataset.generate import GenerateRequest, generate
from mpchair.synth import synthesize_house, write_house
from mpchair.synth.realism import CLEAN

ROOT = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
SEED = 11


@pytest.fixture(scope="module")
def houses(tmp_path_factory) -> tuple[Path, str]:
    root = tmp_path_factory.mktemp("houses")
    # Clean: the attempt-limit case needs a house whose first viewpoint is invalid, as this clean one's is.
    house = synthesize_house(7, levels=1, realism=CLEAN)
    write_house(root, house)
    return root, house.id


def _req(houses, out: Path, frames: int, **kw) -> GenerateRequest:
    root, hid = houses
    return GenerateRequest(root=root, houses=(hid,), frames=frames, out=out, seed=SEED, progress=False, **kw)


def _cmd(houses, out: Path, frames: int, *extra: str) -> list[str]:
    root, hid = houses
    return [sys.executable, "-m", "mpchair.cli", "generate", "--root", str(root), "--house", hid, "--frames",
            str(frames), "--out", str(out), "--seed", str(SEED), "--quiet", *extra]


def _cli(main, args: list, capsys) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    out, err = capsys.readouterr()
    return e.value.code, out, err


def _one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    return lines[0]


def _children(pid: int) -> list[int]:
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except FileNotFoundError:
        return []


def _wait_for(cond, proc: subprocess.Popen) -> None:
    """Poll until ``cond()`` (the test fails if ``proc`` ends first or nothing happens for minutes)."""
    deadline = time.monotonic() + 300
    while not cond():
        assert proc.poll() is None, "the command ended before the fault could be injected"
        assert time.monotonic() < deadline, "the command made no progress"
        time.sleep(0.01)


def _run(cmd: list[str], **kw) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, env=ENV, capture_output=True, text=True, timeout=600, **kw)


def _start(cmd: list[str]) -> subprocess.Popen:
    """Start ``cmd`` in its own process group (stdout dropped, stderr kept)."""
    return subprocess.Popen(cmd, env=ENV, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)


def _finish(proc: subprocess.Popen) -> str:
    """Wait for ``proc`` (a hang fails here) and return its stderr; a test that failed earlier kills its group."""
    try:
        return proc.communicate(timeout=600)[1]
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _reference(houses, tmp_path: Path, frames: int) -> dict[str, bytes]:
    """What an uninterrupted run writes (in this process)."""
    generate(_req(houses, tmp_path / "ref", frames))
    return tree(tmp_path / "ref")


# --- generate -----------------------------------------------------------------------------------------------------


def test_sigkill_before_every_rename_then_the_same_command_resumes_byte_identical(houses, tmp_path):
    frames = 2
    renames = count_replaces(lambda: generate(_req(houses, tmp_path / "ref", frames)), tmp_path / "ref")
    tests = len((tmp_path / "ref" / "ImageSets" / "test.txt").read_text().split())
    # settings, 5 KITTI files + record per frame, ImageSets, the test frames' 3 links in testing/, manifest
    assert renames == 1 + frames * 6 + 3 + 3 * tests + 1 and tests == 1
    want = tree(tmp_path / "ref")
    for k in range(1, renames + 1):
        out = tmp_path / f"k{k}"

        def killed_run(k=k, out=out):
            kill_at_replace(k, out)
            generate(_req(houses, out, frames))

        status = run_forked(killed_run)
        assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL, k
        assert any(p.name.endswith(".tmp") for p in out.rglob("*"))  # killed with a temp file not yet renamed
        summary = generate(_req(houses, out, frames))  # the same command, after SIGKILL at rename k
        assert summary.complete and summary.made + summary.resumed == frames, k
        assert tree(out) == want, k  # no temp or lock file left either


def _stopped(pid: int) -> bool:
    """Whether process ``pid`` is stopped (SIGSTOP: state T in /proc/PID/stat)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0] == "T"
    except (FileNotFoundError, ProcessLookupError):
        return False


def test_ctrl_c_says_how_many_frames_are_kept_and_the_same_command_resumes(houses, tmp_path):
    """Ctrl-C (SIGINT to the job's process group) part-way: exit 130, no traceback, one line saying how many frames
    the folder keeps and to run the same command again; that command ends byte-identical to an uninterrupted run.

    The moment is fixed, not raced: the run stops itself (SIGSTOP) just before renaming frame 2's record into place
    (its five KITTI files written, the record not: the frame is not done), the test sends SIGINT to the group and
    continues it. (A SIGINT sent once two records were seen landed anywhere, after the last frame too, on a machine
    busy enough to starve the test.) A dead temporary of a finished frame, as a writer killed beside the run leaves,
    is removed by the resumed run like any other."""
    frames = 12
    want = _reference(houses, tmp_path, frames)
    out = tmp_path / "out"
    cmd = _cmd(houses, out, frames, "--workers", "1")
    stopped = [sys.executable, str(ROOT / "tests" / "helpers_faults.py"), "--stop", ".frames/000002.json", "--",
               "mpchair", *cmd[3:]]
    # SIGINT as a terminal's Ctrl-C delivers it: not ignored (a job started in the background inherits SIG_IGN, and
    # Python then installs no KeyboardInterrupt handler)
    proc = subprocess.Popen(stopped, env=ENV, start_new_session=True, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        _wait_for(lambda: _stopped(proc.pid), proc)
        os.killpg(proc.pid, signal.SIGINT)
        os.killpg(proc.pid, signal.SIGCONT)
    finally:
        err = _finish(proc)
    assert proc.returncode == 130 and "Traceback" not in err, err
    assert sorted(p.name for p in (out / ".frames").iterdir()) == ["000000.json", "000001.json"]  # no temp record
    assert (out / "training" / "image_2" / "000002.png").is_file()  # frame 2's files, without its record
    assert err.strip().splitlines()[-1] == (f"interrupted: 2 of {frames} frames are kept in {out}: run the same "
                                            "command again to resume")
    (out / "training" / "image_2" / ".000001.png.0123456789ab.tmp").write_bytes(b"\x89PNG half")  # a dead writer's
    res = _run(cmd + ["--json"])
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["resumed"] == 2 and tree(out) == want


def test_a_killed_pool_worker_stops_the_run_with_one_error_line_and_the_run_resumes(houses, tmp_path):
    frames = 12
    want = _reference(houses, tmp_path, frames)
    out = tmp_path / "out"
    cmd = _cmd(houses, out, frames, "--workers", "2")
    proc = _start(cmd)
    try:
        _wait_for(lambda: len(_children(proc.pid)) == 2, proc)
        os.killpg(proc.pid, signal.SIGSTOP)  # freeze the job, so the kill lands while frames are still pending
        workers = _children(proc.pid)
        assert len(list((out / ".frames").glob("*.json"))) < frames
        os.kill(workers[0], signal.SIGKILL)  # as the out-of-memory killer would
        os.killpg(proc.pid, signal.SIGCONT)
    finally:
        err = _finish(proc)
    assert proc.returncode == 1
    line = _one_error_line(err)
    assert f"worker process {workers[0]} was killed by SIGKILL" in line and "run the same command" in line
    assert not Path(f"/proc/{workers[1]}").exists()  # the other worker was stopped, not orphaned
    res = _run(cmd + ["--json"])
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["complete"] and tree(out) == want


def _gone(pid: int, within: float = 10.0) -> bool:
    """Whether process ``pid`` ends (or is a zombie left for its new parent to reap) within ``within`` seconds."""
    deadline = time.monotonic() + within
    while time.monotonic() < deadline:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0]
        except (FileNotFoundError, ProcessLookupError):
            return True
        if state in ("Z", "X"):
            return True
        time.sleep(0.02)
    return False


def test_a_killed_main_process_takes_its_workers_along_and_the_same_command_resumes(houses, tmp_path):
    """SIGKILL to the main process alone (the out-of-memory killer's choice), not its group: its workers end within
    moments instead of blocking on their pipes forever, they never held the folder lock, and the same command runs
    at once and ends byte-identical."""
    frames = 12
    want = _reference(houses, tmp_path, frames)
    out = tmp_path / "out"
    cmd = _cmd(houses, out, frames, "--workers", "2")
    proc = _start(cmd)
    workers: list[int] = []
    survivors: list[int] = []
    try:
        _wait_for(lambda: len(_children(proc.pid)) == 2 and any((out / ".frames").glob("*.json")), proc)
        workers = _children(proc.pid)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        survivors = [w for w in workers if not _gone(w)]
    finally:
        for w in workers if proc.poll() is None or survivors else []:  # a failed test leaves no orphan either
            with contextlib.suppress(ProcessLookupError):
                os.kill(w, signal.SIGKILL)
        if proc.poll() is None:
            proc.kill()
        proc.stderr.close()  # an orphan would hold the pipe open: never wait for its end
        proc.wait()
    assert not survivors, "workers outlived their killed parent"
    assert len(list((out / ".frames").glob("*.json"))) < frames  # killed with frames still to make
    res = _run(cmd + ["--json"])
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["complete"] and tree(out) == want


def _limit_file_size() -> None:
    resource.setrlimit(resource.RLIMIT_FSIZE, (150_000, resource.RLIM_INFINITY))


def test_an_os_error_inside_a_worker_is_one_line_exit_2_and_the_run_resumes(houses, tmp_path):
    """RLIMIT_FSIZE makes the kernel refuse the scans' writes (EFBIG) inside the pool workers; any platform, no root."""
    frames = 4
    want = _reference(houses, tmp_path, frames)
    out = tmp_path / "out"
    cmd = _cmd(houses, out, frames, "--workers", "2")
    res = _run(cmd, preexec_fn=_limit_file_size)
    assert res.returncode == 2
    line = _one_error_line(res.stderr)
    assert f"{out}/training/velodyne/0000" in line and "File too large" in line and "same command" in line
    assert (out / ".generate.json").is_file() and not list((out / ".frames").glob("*.json"))
    res = _run(cmd)
    assert res.returncode == 0, res.stderr
    assert tree(out) == want


@pytest.fixture
def small_disk(tmp_path):
    """A 700 KiB tmpfs (a real ENOSPC); needs the right to mount (root outside a restricted container)."""
    with mounted_tmpfs(tmp_path / "disk", "700k") as disk:
        yield disk


def test_a_full_disk_is_one_line_exit_2_and_the_run_resumes_after_space_is_freed(houses, tmp_path, small_disk):
    frames = 3
    want = _reference(houses, tmp_path, frames)
    out = small_disk / "ds"
    cmd = _cmd(houses, out, frames)
    res = _run(cmd)
    assert res.returncode == 2
    line = _one_error_line(res.stderr)
    assert f"error: {out}/" in line and "No space left on device" in line and "same command" in line
    subprocess.run(["mount", "-o", "remount,size=8m", str(small_disk)], check=True)
    assert _run(cmd).returncode == 0
    assert tree(out) == want

    # The disk fills up while ImageSets and the manifest are written (the state a kill before them leaves).
    (out / "manifest.json").unlink()
    shutil.rmtree(out / "ImageSets")
    st = os.statvfs(small_disk)
    (small_disk / "filler").write_bytes(b"\0" * (st.f_bavail * st.f_frsize - 4096))
    res = _run(cmd)
    assert res.returncode == 2
    assert "No space left on device" in _one_error_line(res.stderr) and not (out / "manifest.json").exists()
    (small_disk / "filler").unlink()
    assert _run(cmd).returncode == 0
    assert tree(out) == want


def test_a_second_generate_on_a_busy_folder_is_refused_and_the_first_finishes(houses, tmp_path, capsys):
    frames = 6
    want = _reference(houses, tmp_path, frames)
    out = tmp_path / "out"
    cmd = _cmd(houses, out, frames)
    first = _start(cmd)
    try:
        _wait_for(lambda: any((out / ".frames").glob("*.json")), first)
        os.killpg(first.pid, signal.SIGSTOP)  # the first run holds the folder, mid-way
        code, _, err = _cli(mpchair_main, cmd[3:], capsys)
        assert code == 2
        line = _one_error_line(err)
        assert line.startswith(f"error: {out}: another mpchair generate") and f"(pid {first.pid})" in line
        code, _, err = _cli(mpchair_main, cmd[3:] + ["--shard", "1/2"], capsys)
        assert code == 2 and "must share N" in _one_error_line(err)
        os.killpg(first.pid, signal.SIGCONT)
    finally:
        err = _finish(first)
    assert first.returncode == 0, err
    assert tree(out) == want


def test_settings_that_cannot_make_frames_leave_nothing_and_the_corrected_command_runs(houses, tmp_path, capsys):
    out = tmp_path / "out"
    base = _cmd(houses, out, 3)[3:]
    for extra, cause in ((["--max-attempts", "1"], "the attempt limit"), (["--robot-radius", "5"], "clearance")):
        code, _, err = _cli(mpchair_main, base + extra, capsys)
        assert code == 2 and cause in _one_error_line(err)
        assert not out.exists()
    for extra in (["--height", "nan"], ["--robot-radius", "inf"], ["--height", "-1"]):
        code, _, err = _cli(mpchair_main, base + extra, capsys)
        assert code == 2 and "must be a finite number" in _one_error_line(err) and not out.exists()
    (tmp_path / "file").write_text("x")
    code, _, err = _cli(mpchair_main, _cmd(houses, tmp_path / "file" / "ds", 3)[3:], capsys)
    assert code == 2 and _one_error_line(err) == (f"error: {tmp_path / 'file'}: is not a folder, so "
                                                  f"{tmp_path / 'file' / 'ds'} cannot be written")
    code, _, err = _cli(mpchair_main, base, capsys)
    assert code == 0 and (out / "manifest.json").is_file()


def test_a_folder_killed_before_its_first_frame_takes_corrected_settings(houses, tmp_path):
    out = tmp_path / "out"
    status = run_forked(lambda: (kill_at_replace(2, out), generate(_req(houses, out, 2, height=1.1))))
    assert os.WTERMSIG(status) == signal.SIGKILL and (out / ".generate.json").is_file()
    generate(_req(houses, out, 2))  # other settings; the folder holds no frame yet
    assert tree(out) == _reference(houses, tmp_path, 2)


# --- detector -----------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return make_tiny_dataset(tmp_path_factory.mktemp("tiny"), n_frames=8, seed=0)


class _Crafted:
    """Pickles as a call of ``os.system`` (what a malicious checkpoint does)."""

    def __init__(self, command: str):
        self.command = command

    def __reduce__(self):
        return os.system, (self.command,)


def test_a_crafted_checkpoint_is_refused_and_runs_nothing(data, tmp_path, capsys):
    cfg = write_test_config(tmp_path / "cfg.yaml", train=dict(batch_size=2, epochs=1))
    crafted = tmp_path / "crafted.pt"
    marker = tmp_path / "marker"
    torch.save({"format": 1, "model": _Crafted(f"touch {marker}")}, crafted)
    # The file is a real attack: unpickled the unsafe way, it runs its command.
    control = tmp_path / "control"
    torch.save({"format": 1, "model": _Crafted(f"touch {control}")}, tmp_path / "control.pt")
    torch.load(tmp_path / "control.pt", weights_only=False)
    assert control.exists()

    run = tmp_path / "run"
    run.mkdir()
    shutil.copy(crafted, run / "last.pt")
    for args in (["eval", "--config", cfg, "--data", data, "--checkpoint", crafted, "--split", "train"],
                 ["bench", "--config", cfg, "--data", data, "--checkpoint", crafted, "--split", "train"],
                 ["train", "--config", cfg, "--data", data, "--out", run, "--resume", "--no-progress"]):
        code, out, err = _cli(detector_main, args, capsys)
        assert code == 2 and "loading it would call posix.system" in _one_error_line(err) and not out, args[0]
        assert not marker.exists()
    assert sorted(p.name for p in run.iterdir()) == ["last.pt"]


def test_a_second_train_on_a_busy_run_folder_is_refused(data, tmp_path, capsys):
    cfg = write_test_config(tmp_path / "cfg.yaml", train=dict(batch_size=2, epochs=1, samples_per_epoch=4))
    run = tmp_path / "run"
    args = ["train", "--config", cfg, "--data", data, "--out", run, "--threads", "1", "--no-progress"]
    first = _start([sys.executable, "-m", "detector", *map(str, args)])
    try:
        _wait_for(lambda: (run / "metrics.jsonl").is_file(), first)
        os.killpg(first.pid, signal.SIGSTOP)
        code, _, err = _cli(detector_main, args + ["--resume"], capsys)
        assert code == 2
        assert _one_error_line(err).startswith(f"error: {run}: another detector train is writing this folder")
        os.killpg(first.pid, signal.SIGCONT)
    finally:
        err = _finish(first)
    assert first.returncode == 0, err
    assert not (run / ".train.lock").exists()


def _records(run: Path) -> list[dict]:
    lines = (run / "metrics.jsonl").read_text().splitlines()
    return [{k: v for k, v in json.loads(line).items() if k != "time_s"} for line in lines]


def test_a_kill_during_evaluation_or_a_checkpoint_write_resumes_to_the_uninterrupted_run(data, tmp_path):
    cfg = write_test_config(tmp_path / "cfg.yaml", train=dict(batch_size=2, epochs=2, eval_every=1,
                                                              samples_per_epoch=4))
    ref = tmp_path / "ref"
    train(cfg, data, ref, threads=1, split="train", eval_split="val", progress=False)
    want = _records(ref)
    assert [r["epoch"] for r in want if r["kind"] == "eval"] == [1, 2]
    for target in ("/last.pt", "eval/epoch_001/metrics.json"):
        run = tmp_path / target.replace("/", "_")
        killed = _run([sys.executable, str(ROOT / "tests" / "helpers_faults.py"), target, "--", "detector", "train",
                       "--config", str(cfg), "--data", str(data), "--out", str(run), "--threads", "1", "--no-progress"])
        assert killed.returncode == -signal.SIGKILL, killed.stderr
        if target == "/last.pt":
            assert list(run.glob(".last.pt.*.tmp"))  # the killed run left its temp checkpoint
        train(cfg, data, run, resume=True, threads=1, progress=False)
        assert _records(run) == want, target
        assert (run / "eval" / "epoch_001" / "metrics.json").read_bytes() == (
            ref / "eval" / "epoch_001" / "metrics.json").read_bytes()
        a = torch.load(ref / "last.pt", weights_only=True)
        b = torch.load(run / "last.pt", weights_only=True)
        assert all(torch.equal(a["model"][k], b["model"][k]) for k in a["model"])
        # byte-identical checkpoints (sha256), also after a resume from the epoch-1 checkpoint: the same pickle (no
        # key memoised differently) and the same saved RNG state
        for rel in ("last.pt", *(str(p.relative_to(ref)) for p in sorted(ref.glob("checkpoints/*.pt")))):
            assert _sha256(run / rel) == _sha256(ref / rel), (target, rel)
        assert not [p for p in run.rglob("*") if ".tmp" in p.name or p.suffix == ".lock"]  # nothing left behind


def test_train_on_a_corrupt_dataset_writes_nothing(data, tmp_path, capsys):
    root = tmp_path / "data"
    shutil.copytree(data, root)
    bad = root / "training" / "velodyne" / "000005.bin"
    bad.write_bytes(bad.read_bytes()[:10])
    cfg = write_test_config(tmp_path / "cfg.yaml", train=dict(batch_size=2, epochs=1))
    for gt_sampling in (True, False):
        write_test_config(cfg, data=dict(gt_sampling=dict(enabled=gt_sampling)), train=dict(batch_size=2, epochs=1))
        code, _, err = _cli(detector_main, ["train", "--config", cfg, "--data", root, "--out", tmp_path / "run",
                                            "--no-progress"], capsys)
        assert code == 2 and _one_error_line(err) == (f"error: {bad}: size 10 bytes is not a multiple of 16 "
                                                      "(float32 x, y, z, r rows)")
        assert not (tmp_path / "run").exists()


@pytest.mark.parametrize(("workers", "bad", "out"), [(0, "scan", "empty"), (2, "scan", "new"), (2, "label", "new")])
def test_bad_input_only_the_loader_reads_is_one_line_with_or_without_workers(data, tmp_path, workers, bad, out):
    # What the pre-run check cannot see (it sizes scans without reading them; GT sampling off, so nothing loads every
    # frame first): a NaN in a scan, a chair of height 0. Met in a DataLoader worker, torch re-raised it with the
    # worker's traceback as its message (the third audit's leftover); now the main process raises the same error.
    root = tmp_path / "data"
    shutil.copytree(data, root)
    if bad == "scan":
        path = root / "training" / "velodyne" / "000001.bin"
        points = np.fromfile(path, dtype="<f4").reshape(-1, 4)
        points[3, 1] = np.nan
        points.tofile(path)
        want = f"error: {path}: point 3 has a non-finite y (nan); a scan holds finite x, y, z, reflectance"
    else:
        path = root / "training" / "label_2" / "000001.txt"
        lines = path.read_text().splitlines()
        tokens = lines[0].split()
        tokens[8] = "0"  # h
        path.write_text("\n".join([" ".join(tokens), *lines[1:]]) + "\n")
        want = f"error: {path}: an object has a non-positive dimension (h, w, l must be > 0)"
    cfg = write_test_config(tmp_path / "cfg.yaml", data=dict(gt_sampling=dict(enabled=False)),
                            train=dict(batch_size=2, epochs=1, num_workers=workers))
    run = tmp_path / "new" / "run" if out == "new" else tmp_path / "empty"
    if out == "empty":
        run.mkdir()
    r = _run([sys.executable, "-m", "detector", "train", "--config", str(cfg), "--data", str(root), "--out", str(run),
              "--threads", "1", "--no-progress"])
    assert r.returncode == 2 and _one_error_line(r.stderr) == want
    # a new run that failed before its first checkpoint leaves nothing: the folders it made are gone, a folder that
    # was there before stays (empty, as it was)
    if out == "new":
        assert not (tmp_path / "new").exists()
    else:
        assert run.is_dir() and not any(run.iterdir())
