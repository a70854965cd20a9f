"""``detector stream-eval``: streaming AP (sAP) of a detector on a moving robot's stream (parse, call, print)."""

from __future__ import annotations

import json
from pathlib import Path

import click

from detector.commands import PRETRAINED_HELP, config_help
from mpchair.core import limits
from mpchair.core.atomic import check_writable
from mpchair.core.errors import InputError


@click.command("stream-eval", context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 110})
@click.option("--data", required=True, type=click.Path(path_type=Path), help="Stream folder (mpchair stream).")
@click.option("--config", type=click.Path(path_type=Path), metavar="NAME|YAML",
              help=config_help("Experiment config of the model"))
@click.option("--checkpoint", type=click.Path(path_type=Path),
              help=f"Trained checkpoint of the model ({PRETRAINED_HELP}).")
@click.option("--results", type=click.Path(path_type=Path),
              help="Offline outputs of any detector: RESULTS/NN/NNNNNN.txt, 16-column KITTI result files.")
@click.option("--oracle", is_flag=True, help="A perfect detector: each frame's own labels with score 1.")
@click.option("--latency", "latency_kind", default=None, metavar="measured|LOG.json",
              help="measured: time the model per processed frame on this machine (the default for a model); or a "
                   "latency log written by --latency-log, replayed exactly.")
@click.option("--latency-log", type=click.Path(path_type=Path), default=None,
              help="With measured latency: write the per-frame latencies (and the machine) to this JSON file.")
@click.option("--save-results", type=click.Path(path_type=Path), default=None,
              help="Write the outputs as result files (the --results layout; with --no-offline only the processed "
                   "frames'), to rescore without the model. A folder this option saved before is replaced; any other "
                   "non-empty folder is refused.")
@click.option("--offline/--no-offline", default=True, show_default=True,
              help="Run the model on every frame for the offline AP; --no-offline runs it only on processed frames.")
@click.option("--latency-ms", type=float, default=None, help="A constant latency for every frame, milliseconds.")
@click.option("--mode", type=click.Choice(["ego", "raw"]), default="ego", show_default=True,
              help="ego: move stale boxes by the robot's relative pose (perfect odometry); raw: use them as they are.")
@click.option("--schedule", type=click.Choice(["single", "unbounded"]), default="single", show_default=True,
              help="single: one worker takes the latest frame when idle; unbounded: every frame processed on arrival.")
@click.option("--repeats", default=3, show_default=True, type=click.IntRange(1, 1000),
              help="Measured latency: median of this many runs per frame (at most 1000).")
@click.option("--warmup", default=10, show_default=True, type=click.IntRange(0, 10_000),
              help="Measured latency: untimed runs before the first timed one (at most 10000).")
@click.option("--threads", type=limits.parallel_range(), default=None, help="torch CPU threads.")
@click.option("--device", default="cpu", show_default=True, help="cpu or cuda.")
@click.option("--json", "as_json", is_flag=True, help="Print the summary as JSON instead of the table.")
@click.option("--json-out", "json_out", type=click.Path(path_type=Path), default=None,
              help="Also write the summary as JSON to this file (the table is still printed).")
@click.option("--rerun", "rerun_out", type=click.Path(path_type=Path), default=None,
              help="Also write a Rerun recording (.rrd): points, labels, pose and the boxes the detector had at each "
                   "moment, stale and ego-compensated (needs the rerun extra).")
@click.option("--mcap", "mcap_out", type=click.Path(path_type=Path), default=None,
              help="Also write a ROS 2 bag (.mcap, for Foxglove or ros2 bag play): the stream's points, tf and labels, "
                   "and per frame the boxes the detector had, as emitted (/detections/<model>) and ego-compensated "
                   "(/detections/<model>/ego) (needs the ros extra).")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def stream_eval(data, config, checkpoint, results, oracle, latency_kind, latency_log, save_results, offline,
                latency_ms, mode, schedule, repeats, warmup, threads, device, as_json, json_out, rerun_out, mcap_out,
                quiet) -> None:
    """Streaming AP: score each frame of a robot's stream with the latest output the detector had emitted by its
    capture time, pooled over all frames with the KITTI evaluator (Chair, 3D and BEV, IoU 0.5, R40 and R11, every
    box counted).

    \b
    Examples:
      detector stream-eval --data stream/ --config mpchair_sparse_cpu \\
                           --checkpoint runs/sparse/last.pt --threads 2 --json-out sparse-ego.json
      detector stream-eval --data stream/ --oracle --latency-ms 300 --mode raw
      detector stream-eval --data stream/ --results offline/ --latency-ms 120 --rerun stream.rrd
      detector stream-eval --data stream/ --oracle --latency-ms 300 --mcap oracle.mcap
    """
    from detector.stream import prepare, read_stream, score
    from detector.stream.run import read_latency_log, source_from_options
    from detector.stream.run import save_results as write_results

    if latency_kind is not None and latency_ms is not None:
        raise InputError("give either --latency or --latency-ms, not both")
    replay = None
    if latency_kind is not None and latency_kind != "measured":
        replay = read_latency_log(latency_kind)
    if latency_log is not None and (replay is not None or latency_ms is not None):
        raise InputError("--latency-log records measured latencies; it cannot go with --latency-ms or a replayed log")
    if rerun_out is not None:
        from mpchair.recording.rerun import check_rerun_path

        check_rerun_path(rerun_out)
    if mcap_out is not None:
        from mpchair.recording.mcap import check_mcap_path

        check_mcap_path(mcap_out)
    if json_out is not None and json_out.suffix.lower() != ".json":
        raise InputError("--json-out must name a .json file", json_out)
    for output in (json_out, latency_log):
        if output is not None:
            check_writable(output)
    if save_results is not None:
        from detector.stream.run import check_save_results

        check_save_results(save_results, results)  # missing, empty or this command's own; never --results itself
    source = source_from_options(config, checkpoint, results, oracle, device, threads)
    stream = read_stream(data)
    prep = prepare(stream, source, latency_ms=latency_ms, latency_log=replay, schedule=schedule, repeats=repeats,
                   warmup=warmup, offline=offline, progress=not quiet)
    summary = score(prep, mode)
    wrote: list[str] = []  # one "wrote FILE: what" line per file written, after the table
    if save_results is not None:
        write_results(prep, save_results)
        wrote.append(f"wrote {save_results}: the outputs as KITTI result files (rescore them with --results)")
    if latency_log is not None:
        from mpchair.core.atomic import write_text

        write_text(latency_log, json.dumps(prep.latency_log, sort_keys=True, indent=1) + "\n")
        wrote.append(f"wrote {latency_log}: the measured latencies (replay them with --latency {latency_log})")
    text = json.dumps(summary, sort_keys=True, indent=1) + "\n"
    if rerun_out is not None:
        from detector.stream.rerun import log_stream_eval

        info = log_stream_eval(prep, rerun_out)
        wrote.append(f"wrote {rerun_out}: {info['frames']} frames with the detector's boxes "
                     f"(open it with: rerun {rerun_out})")
    if mcap_out is not None:
        from detector.stream.mcap import log_stream_eval as log_stream_eval_bag

        info = log_stream_eval_bag(prep, mcap_out)
        wrote.append(f"wrote {mcap_out}: {info['frames']} frames, {sum(info['topics'].values())} messages on "
                     f"{len(info['topics'])} topics (open it in Foxglove, or replay it: ros2 bag play -s mcap "
                     f"{mcap_out})")
    if json_out is not None:
        from mpchair.core.atomic import write_text

        write_text(json_out, text)
        wrote.append(f"wrote {json_out}: the summary as JSON")
    if as_json:
        click.echo(text, nl=False)
    else:
        click.echo(format_summary(summary))
    for line in wrote:  # as mpchair view says it; on stderr when stdout is the JSON
        click.echo(line, err=as_json)


def format_summary(s: dict) -> str:
    """A short human-readable table of a stream-eval summary."""
    lines = [f"streaming evaluation: {s['frames']} frames in {s['sequences']} sequences at {s['rate_hz']:g} Hz, "
             f"mode {s['mode']}, schedule {s['schedule']}"]
    for cls, m in s["sAP"].items():
        lines.append(f"{cls} ({s['num_gt'][cls]} boxes)        R40 3D    R40 BEV    R11 3D    R11 BEV")
        if s["offline_AP"] is not None:
            off = s["offline_AP"][cls]
            lines.append(f"  offline AP          {off['3d']['R40']:8.2f} {off['bev']['R40']:10.2f} "
                         f"{off['3d']['R11']:9.2f} {off['bev']['R11']:10.2f}")
        lines.append(f"  sAP                 {m['3d']['R40']:8.2f} {m['bev']['R40']:10.2f} "
                     f"{m['3d']['R11']:9.2f} {m['bev']['R11']:10.2f}")
        ceiling = s.get("ap_ceiling", {}).get(cls)
        if ceiling is not None and ceiling["R40"] < 100.0:
            # KITTI fills one recall slot per true positive: with under 41 boxes even a perfect detector is below 100
            lines.append(f"  ceiling (perfect)   {ceiling['R40']:8.2f} {ceiling['R40']:10.2f} "
                         f"{ceiling['R11']:9.2f} {ceiling['R11']:10.2f}   (fewer than 41 boxes: KITTI's recall slots)")
    lat, st, sf = s["latency_ms"], s["staleness_ms"], s["staleness_frames"]
    fmt = lambda x: "-" if x is None else f"{x:.1f}"  # noqa: E731
    lines.append(f"latency ms: median {fmt(lat['median'])}, p95 {fmt(lat['p95'])}; staleness: mean {fmt(st['mean'])} "
                 f"ms ({fmt(sf['mean'])} frames), p95 {fmt(st['p95'])} ms ({fmt(sf['p95'])} frames)")
    # "in time" alone read as a failure at any latency: a query is scored at its frame's capture time, when that
    # frame's own output cannot exist yet unless the latency is 0, so its answer is an earlier frame's (staleness)
    lines.append(f"frames processed {100 * s['frames_processed']:.1f} % (the others arrived while the detector was "
                 f"busy); queries answered by their own frame {100 * s['in_time']:.1f} % (needs zero latency: "
                 "otherwise an earlier frame's output answers, as the staleness says); queries without output "
                 f"{s['queries_without_output']}")
    return "\n".join(lines)
