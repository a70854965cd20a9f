"""One step of the GPU check: a command run as a subprocess against the check's deadline
(``DEVICE_CHECK_DEADLINE``), its output passed through, its status and time recorded as ``RESULTS/steps/NAME.json``.
Loads no torch: it wraps every step of the check."""

from __future__ import annotations

import argparse
import collections
import os
import shlex
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from mpchair.core.atomic import write_text
from reproduction.checkout import ROOT
from reproduction.device_check.files import write_json


def _pump(stream, sink, keep: collections.deque | None, lines: list[str] | None) -> None:
    """Copy a child's text stream to ``sink`` line by line as it comes, keeping the tail and/or every line."""
    for line in stream:
        sink.write(line)
        sink.flush()
        if keep is not None:
            keep.append(line)
        if lines is not None:
            lines.append(line)


def cmd_step(args: argparse.Namespace) -> int:
    """Run ``args.cmd`` as one step of the check: its output passes through; stdout goes to ``--stdout`` too; the
    step's status, time and (on failure) stderr tail go to ``RESULTS/steps/NAME.json``. Exit status: the child's."""
    record = {"name": args.name, "command": shlex.join(args.cmd), "seconds": 0.0, "returncode": None}
    deadline = float(os.environ.get("DEVICE_CHECK_DEADLINE", "inf"))
    left = deadline - time.time()
    if left < 5:
        record.update(status="skipped", reason="the check's time budget (--budget) was spent before this step")
        write_json(Path(args.results) / "steps" / f"{args.name}.json", record)
        print(f"[{args.name}] skipped: time budget spent", file=sys.stderr)
        return 0
    print(f"[{args.name}] {record['command']}", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    # its own process group, so that a timeout also ends what it started (torchrun's workers, DataLoader workers)
    proc = subprocess.Popen(args.cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                            start_new_session=True)
    tail: collections.deque = collections.deque(maxlen=40)
    out_lines: list[str] = []
    pumps = [threading.Thread(target=_pump, args=(proc.stdout, sys.stdout, None, out_lines)),
             threading.Thread(target=_pump, args=(proc.stderr, sys.stderr, tail, None))]
    for t in pumps:
        t.start()
    try:
        rc = proc.wait(timeout=min(args.timeout, left))
        timed_out = False
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        rc, timed_out = proc.wait(), True
    for t in pumps:
        t.join()
    record.update(seconds=round(time.perf_counter() - t0, 2), returncode=rc,
                  status="ok" if rc == 0 and not timed_out else "failed")
    if timed_out:
        record["reason"] = f"stopped after {min(args.timeout, left):.0f} s (step timeout or the check's budget)"
    if record["status"] != "ok":
        record["stderr_tail"] = "".join(tail)[-4000:]
    if args.stdout:
        write_text(args.stdout, "".join(out_lines))
    write_json(Path(args.results) / "steps" / f"{args.name}.json", record)
    return 0 if record["status"] == "ok" else (rc or 1)
