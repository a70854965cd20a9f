"""``detector bench``: every component timed (positive), the JSON schema, the ratio row, the CLI's error path; the
progress bars of ``bench`` and ``ops`` (on a terminal only)."""

from __future__ import annotations

import io
import json
import sys
from pathlib import Path

import click.testing
import pytest
import torch
from helpers_detector import make_tiny_dataset, write_test_config

from detector.bench import COMPONENTS, SHARED, BenchResult, format_table, ratio_rows, time_shared
from detector.checkpoint import Checkpoint, load_model, save_checkpoint
from detector.cli import cli, main
from detector.config import load_experiment, pseudoimage_geometry
from detector.data.experiment import load_eval_frames
from detector.models import build_model
from mpchair.geometry import frame_density

DENSE = "detector/configs/mpchair_dense_smoke.yaml"
SPARSE = "detector/configs/mpchair_sparse_smoke.yaml"


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return make_tiny_dataset(tmp_path_factory.mktemp("bench") / "ds", n_frames=3)


def test_bench_json_prints_to_stdout_and_json_out_writes_a_file(data, tmp_path) -> None:
    """One meaning per flag: ``--json`` prints the result to stdout (no table), ``--json-out FILE`` writes it."""
    out = tmp_path / "bench.json"
    args = ["bench", "--config", DENSE, "--data", str(data), "--frames", "1", "--trials", "1", "--warmup", "0",
            "--threads", "1", "--no-progress"]
    res = click.testing.CliRunner().invoke(cli, [*args, "--json", "--json-out", str(out)])
    assert res.exit_code == 0, res.output
    printed = json.loads(res.stdout)
    assert printed == json.loads(out.read_text()) and [m["name"] for m in printed["models"]] == ["dense"]
    res = click.testing.CliRunner().invoke(cli, [*args, "--json", str(out)])  # the old file-taking form
    assert res.exit_code == 2 and "unexpected extra argument" in res.output


def test_bench_cli_json_schema_and_table(data, tmp_path) -> None:
    out = tmp_path / "bench.json"
    res = click.testing.CliRunner().invoke(cli, [
        "bench", "--config", DENSE, "--config", SPARSE, "--data", str(data), "--frames", "2", "--trials", "2",
        "--warmup", "1", "--threads", "1", "--json-out", str(out)])
    assert res.exit_code == 0, res.output
    result = json.loads(out.read_text())
    assert set(result) == {"models", "skipped", "headline", "density", "machine", "protocol"}
    assert [m["name"] for m in result["models"]] == ["dense", "sparse"]
    for m in result["models"]:
        assert set(m["components"]) == set(COMPONENTS) == {
            "to_device", "feature_extract", "feature_net", "backbone", "head", "bbox_extract", "total"}
        for key, v in m["components"].items():
            assert set(v) == {"mean_ms", "std_ms"}
            assert v["mean_ms"] > 0 and v["std_ms"] >= 0, key
        parts = sum(m["components"][k]["mean_ms"] for k in COMPONENTS[:-1])
        assert m["components"]["total"]["mean_ms"] == pytest.approx(parts, rel=1e-9)  # stamps telescope
        assert m["weights"].startswith("random")
        assert m["page_faults_per_frame"] >= 0
        by = m["page_faults_per_frame_by_component"]  # the stages' counts telescope to the frame's
        assert set(by) == set(COMPONENTS) and by["total"] == pytest.approx(sum(by[k] for k in COMPONENTS[:-1]))
        assert by["total"] <= m["page_faults_per_frame"]
    assert result["protocol"]["frames"] == 2 and result["protocol"]["trials"] == 2
    assert result["protocol"]["frame_ids"] == ["000000", "000001"]
    mach = result["machine"]
    assert mach["torch_threads"] == 1 and set(mach["malloc_env"]) == {"MALLOC_MMAP_MAX_", "MALLOC_TRIM_THRESHOLD_"}
    # density: the same pillar rule as the voxelizer, over the 96 x 64 canvas
    cfg = load_experiment(DENSE)
    frames = load_eval_frames(cfg, data, "test", 2)
    ds = sorted(frame_density(f.points, pseudoimage_geometry(cfg.model))[2] for f in frames)
    assert result["density"]["min"] == pytest.approx(ds[0]) and result["density"]["max"] == pytest.approx(ds[-1])
    assert 0 < ds[0] < 1 and result["density"]["geometry"]["output_shape"] == [96, 64]
    # ratio row: dense / sparse of the means, printed
    typed = BenchResult.from_json(result)
    assert json.dumps(typed.to_json(), indent=2) + "\n" == out.read_text()  # the one definition reads what it wrote
    (name, ratios), = ratio_rows(typed)
    assert name == "dense / sparse"
    d, s = (m["components"]["backbone"]["mean_ms"] for m in result["models"])
    assert ratios["backbone"] == pytest.approx(d / s)
    assert "dense / sparse" in res.output and "Feature Extract" in res.output
    md = format_table(typed, markdown=True)
    assert md.splitlines()[0].startswith("| model | To Device |") and md.count("\n| ") >= 3
    # the shared components, timed back to back too: their own rows and ratio row, after the per-frame table
    assert result["protocol"]["back_to_back"] == list(SHARED) == ["head", "bbox_extract"]
    for m in result["models"]:
        assert set(m["back_to_back"]) == set(SHARED)
        assert all(v["mean_ms"] > 0 and v["std_ms"] >= 0 for v in m["back_to_back"].values())
    (name, ratios), = ratio_rows(typed, "back_to_back")
    d, s = (m["back_to_back"]["bbox_extract"]["mean_ms"] for m in result["models"])
    assert name == "dense / sparse" and set(ratios) == set(SHARED) and ratios["bbox_extract"] == pytest.approx(d / s)
    text = format_table(typed)
    back = text[text.index("timed back to back"):].splitlines()
    h = next(i for i, line in enumerate(back) if line.startswith("model"))  # after the title (wrapped) and a blank
    assert back[h - 1] == "" and all(len(line) <= 118 for line in back[:h])
    assert back[h].split() == ["model", "Head", "BBox", "Extract"] and back[h + 3].startswith("dense / sparse")
    assert f"{ratios['head']:.2f}x" in back[h + 3] and "| model | Head | BBox Extract |" in md


def test_shared_components_run_back_to_back_in_rotated_order(data) -> None:
    """time_shared runs every model to its neck, then every Head, then every BBox Extract, starting at ``first``."""
    cfgs = [load_experiment(c) for c in (DENSE, SPARSE, DENSE)]
    models = [build_model(c.model).eval() for c in cfgs]
    calls = []
    for j, m in enumerate(models):  # record the call order of the real stages
        m.head = lambda *a, j=j, f=m.head: calls.append(("head", j)) or f(*a)
        m.postprocess = lambda *a, j=j, f=m.postprocess: calls.append(("bbox", j)) or f(*a)
    points = [load_eval_frames(c, data, "test", 1)[0].points for c in cfgs]
    ms = time_shared(models, points, torch.device("cpu"), first=2)
    assert calls == [("head", 2), ("head", 0), ("head", 1), ("bbox", 2), ("bbox", 0), ("bbox", 1)]
    assert ms.shape == (3, len(SHARED)) and (ms > 0).all()


def test_bench_checkpoint_count_must_match(data) -> None:
    res = click.testing.CliRunner().invoke(cli, [
        "bench", "--config", DENSE, "--config", SPARSE, "--checkpoint", "x.pt", "--data", str(data)])
    assert res.exit_code != 0 and "one --checkpoint per --config" in str(res.exception or res.output)


def test_bench_checkpoint_times_the_trained_weights(data, tmp_path) -> None:
    """``--checkpoint`` per ``--config`` ('-' = random weights) loads those weights into the timed model. The dense
    checkpoint here has its class bias raised so that every anchor scores 0.88: its model detects on every frame, as
    many boxes as the checkpoint's own model predicts, while random weights (prior 0.01, threshold 0.1) never do."""
    cfg = load_experiment(DENSE)
    torch.manual_seed(0)
    model = build_model(cfg.model)
    with torch.no_grad():
        model.anchor_head.conv_cls.bias.fill_(2.0)
    ckpt = tmp_path / "dense.pt"
    save_checkpoint(ckpt, Checkpoint.capture(model=model, optimizer=torch.optim.AdamW(model.parameters()), cfg=cfg,
                                             epoch=0, step_in_epoch=0, step=0, global_batch=1))
    out = tmp_path / "bench.json"
    res = click.testing.CliRunner().invoke(cli, [
        "bench", "--config", DENSE, "--config", SPARSE, "--checkpoint", str(ckpt), "--checkpoint", "-", "--data",
        str(data), "--frames", "2", "--trials", "1", "--warmup", "0", "--threads", "1", "--json-out", str(out)])
    assert res.exit_code == 0, res.output
    trained, untrained = json.loads(out.read_text())["models"]
    assert trained["weights"] == str(ckpt) and untrained["weights"].startswith("random")
    loaded = load_model(cfg, ckpt)
    expected = sum(len(loaded.predict([torch.from_numpy(f.points)])[0].boxes)
                   for f in load_eval_frames(cfg, data, "test", 2))
    assert trained["detections_per_frame"] == expected / 2 > 0 and untrained["detections_per_frame"] == 0
    # a checkpoint of another architecture is refused before anything is timed
    res = click.testing.CliRunner().invoke(cli, [
        "bench", "--config", SPARSE, "--checkpoint", str(ckpt), "--data", str(data), "--frames", "1", "--trials", "1",
        "--json-out", str(tmp_path / "no.json")])
    assert res.exit_code != 0 and "checkpoint does not fit the config's model" in str(res.exception)
    assert not (tmp_path / "no.json").exists()


def test_bench_threads_default_to_the_free_cores_and_warn_when_oversubscribed(data, tmp_path, capsys,
                                                                              monkeypatch) -> None:
    """``--threads`` defaults to the cores minus the 1-minute load (at least 1); threads + load above the cores is one
    warning line on stderr before the timing (a loaded machine collapsed the sparse/dense ratio from 14.2x to 2.2x)."""
    from detector import device

    assert [device.free_cores(16, load) for load in (0.0, 0.3, 3.6, 15.2, 40.0)] == [16, 16, 12, 1, 1]
    assert device.oversubscription_warning(2, 2, 0.3) is None and device.oversubscription_warning(3, 4, 1.2) is None
    assert device.oversubscription_warning(2, 2, 1.5) == (
        "--threads 2 + load 1.5 exceed the 2 cores: timings will be slower than on an idle machine, the sparse "
        "backbone's most (use --threads 1 or a quiet machine)")
    monkeypatch.setattr(device, "usable_cores", lambda: 4)

    def bench(load: float, *threads: str) -> tuple[list[str], dict]:
        monkeypatch.setattr(device, "load_1m", lambda: load)
        with pytest.raises(SystemExit) as e:
            main(["bench", "--config", DENSE, "--data", str(data), "--frames", "1", "--trials", "1", "--warmup", "0",
                  *threads, "--json-out", str(tmp_path / "b.json")])
        assert e.value.code == 0
        return capsys.readouterr().err.splitlines(), json.loads((tmp_path / "b.json").read_text())["machine"]

    try:
        err, machine = bench(1.2)
        assert machine["torch_threads"] == 3 and not [ln for ln in err if ln.startswith("warning:")], err
        err, machine = bench(3.5, "--threads", "2")
        assert machine["torch_threads"] == 2
        assert [ln for ln in err if ln.startswith("warning:")] == [
            "warning: --threads 2 + load 3.5 exceed the 4 cores: timings will be slower than on an idle machine, the "
            "sparse backbone's most (use --threads 1 or a quiet machine)"]
    finally:
        torch.set_num_threads(1)


def test_a_checkpoint_is_compared_with_the_config_it_is_loaded_under(data, tmp_path, capsys) -> None:
    """A checkpoint loaded under another grid runs (exit 0) with one warning naming the keys that differ; under
    another network it is one error line naming the differing key (exit 2, no PyTorch "Missing key(s)" dump); a file
    that is no checkpoint is one line naming it, without torch's advice to load it unsafely."""
    trained = write_test_config(tmp_path / "trained.yaml")
    cfg = load_experiment(trained)
    model = build_model(cfg.model)
    ckpt = tmp_path / "run.pt"
    save_checkpoint(ckpt, Checkpoint.capture(model=model, optimizer=torch.optim.AdamW(model.parameters()), cfg=cfg,
                                             epoch=0, step_in_epoch=0, step=0, global_batch=1))
    coarse = write_test_config(tmp_path / "coarse.yaml", model=dict(voxel_size=[0.2, 0.2, 4.0], output_shape=[48, 32]))
    narrow = write_test_config(tmp_path / "narrow.yaml", model=dict(layer_channels=[32, 32, 32]))

    def bench(config: Path, checkpoint: Path) -> tuple[int, list[str]]:
        with pytest.raises(SystemExit) as e:
            main(["bench", "--config", str(config), "--checkpoint", str(checkpoint), "--data", str(data), "--frames",
                  "1", "--trials", "1", "--warmup", "0", "--threads", "1", "--json-out", str(tmp_path / "b.json")])
        return e.value.code, capsys.readouterr().err.splitlines()

    code, err = bench(trained, ckpt)
    assert code == 0 and not [ln for ln in err if ln.startswith("warning:")], err
    code, err = bench(coarse, ckpt)
    assert code == 0
    assert [ln for ln in err if ln.startswith("warning:")] == [
        f"warning: {ckpt}: trained under another config (model.voxel_size is [0.1, 0.1, 4.0] in the checkpoint, "
        "[0.2, 0.2, 4.0] here; model.output_shape is [96, 64] in the checkpoint, [48, 32] here; anchors are placed at "
        "the head map's cell centres (model.anchor_centres: cells) because the weights move to another grid); its "
        "weights load "
        "into this one, but results may differ from the trained model's"]
    # the documented move (make reproduce's 288 x 144 weights timed at 768 x 512): the same pillars over a larger
    # grid is one plain line; in --rate mode, whose rows run in fresh processes, too (no UserWarning source line)
    wide = write_test_config(tmp_path / "wide.yaml", model=dict(output_shape=[128, 96]))
    short = (f"warning: {ckpt}: weights trained on the 96 x 64 grid run on this config's 128 x 96 grid (same "
             "pillars, larger area; anchors at the head map's cell centres)")
    code, err = bench(wide, ckpt)
    assert code == 0 and [ln for ln in err if "warning" in ln.lower()] == [short], err
    with pytest.raises(SystemExit) as e:
        main(["bench", "--config", str(wide), "--checkpoint", str(ckpt), "--data", str(data), "--frames", "1",
              "--warmup", "0", "--threads", "1", "--rate", "4", "--duration", "0.5"])
    err = capsys.readouterr().err.splitlines()
    assert e.value.code == 0 and [ln for ln in err if "warning" in ln.lower()] == [short], err
    code, err = bench(narrow, ckpt)
    assert code == 2 and err == [f"error: {ckpt}: checkpoint does not fit the config's model: model.layer_channels is "
                                 "[32, 32, 64] in the checkpoint, [32, 32, 32] here"]
    code, err = bench(trained, trained)  # the YAML given as the checkpoint
    assert code == 2 and len(err) == 1 and err[0].startswith(f"error: {trained}: not a detector checkpoint")
    assert "weights_only" not in err[0]


class _Terminal(io.StringIO):
    """An interactive stderr as tqdm sees it: a stream that says it is a TTY (bars are drawn only on one)."""

    def isatty(self) -> bool:
        return True


def _run(args: list[str], capsys, monkeypatch, *, terminal: bool) -> tuple[int, str, str]:
    """(exit code, stdout, stderr) of ``detector ARGS``, stderr a terminal or (capsys) a pipe."""
    term = _Terminal()
    with monkeypatch.context() as m:
        if terminal:
            m.setattr(sys, "stderr", term)
        with pytest.raises(SystemExit) as e:
            main(args)
    out, err = capsys.readouterr()
    return e.value.code, out, term.getvalue() if terminal else err


def test_bench_and_ops_show_progress_on_a_terminal_unless_told_not_to(data, capsys, monkeypatch) -> None:
    """Both take minutes on real data: on a terminal they draw bars on stderr by default (loading, then bench's
    warm-up and trials or ops' counting); never with --no-progress, on a pipe, or with ops --json; stdout is the
    same table either way."""
    bench = ["bench", "--config", DENSE, "--data", str(data), "--frames", "2", "--trials", "2", "--warmup", "1",
             "--threads", "1"]
    ops = ["ops", "--config", SPARSE, "--data", str(data), "--frames", "2"]
    for args, bars in ((bench, ("loading frames", "bench warm-up", "bench trial 1/2", "bench trial 2/2")),
                       (ops, ("loading frames", "counting ops"))):
        code, shown, err = _run(args, capsys, monkeypatch, terminal=True)
        assert code == 0 and all(b in err for b in bars), (bars, err)
        code, quiet, err = _run([*args, "--no-progress"], capsys, monkeypatch, terminal=True)
        assert code == 0 and err == ""
        code, piped, err = _run(args, capsys, monkeypatch, terminal=False)
        assert code == 0 and err == ""
        if args is ops:
            assert shown == quiet == piped
        else:  # the timings (and so the column widths) differ, the table's columns and rows do not
            heads = [[ln.split()[0] for ln in text.splitlines() if ln.strip()] for text in (shown, quiet, piped)]
            assert heads[0] == heads[1] == heads[2] and shown.split()[:3] == ["model", "To", "Device"]
    code, out, err = _run([*ops, "--json"], capsys, monkeypatch, terminal=True)
    assert code == 0 and err == "" and json.loads(out)["data"]["split"] == "test"


def test_detector_gemm_is_read_once_by_the_cli(data, tmp_path, capsys, monkeypatch) -> None:
    """``DETECTOR_GEMM``: the CLI reads it and runs the command under that library (the bench's machine record names
    it), the choice ends with the command; a bad value is one error line, exit 2, before any work."""
    from detector.ops import gemm

    monkeypatch.setenv("DETECTOR_GEMM", "fast")
    with pytest.raises(SystemExit) as e:
        main(["bench", "--config", DENSE, "--data", str(data), "--json-out", str(tmp_path / "no.json")])
    assert e.value.code == 2 and not (tmp_path / "no.json").exists()
    assert capsys.readouterr().err == ("error: environment variable DETECTOR_GEMM='fast': choose auto or mkl (or unset "
                                       "it)\n")
    monkeypatch.setenv("DETECTOR_GEMM", "mkl")
    try:
        with pytest.raises(SystemExit) as e:
            main(["bench", "--config", DENSE, "--data", str(data), "--frames", "1", "--trials", "1", "--warmup", "0",
                  "--threads", "1", "--json-out", str(tmp_path / "b.json")])
    finally:
        torch.set_num_threads(1)
    assert e.value.code == 0
    assert json.loads((tmp_path / "b.json").read_text())["machine"]["gemm"] == "mkl"
    assert gemm.current_backend() == "auto"


def test_a_runtime_by_precision_table_fits_a_terminal() -> None:
    """``bench --runtime --precision``'s text output (the committed run's deploy result, 21 rows): one table per
    runtime x precision under its heading, every table line within 120 columns (the single table was ~170), the
    group's ratios as ratio_rows gives them; --markdown stays one table with every digit."""
    result = BenchResult.from_json(json.loads((Path(__file__).resolve().parents[1] / "docs" / "results-data" /
                                               "results" / "deploy_bench.json").read_text()))
    text = format_table(result)
    tables_part = text[: text.index("\nheadline: ")]
    assert max(len(line) for line in tables_part.splitlines()) <= 120
    groups = list(dict.fromkeys((m.runtime, m.precision) for m in result.models))
    assert len(groups) > 1 and all(f"{r} {p}:" in tables_part.splitlines() for r, p in groups)
    ratios = dict(ratio_rows(result))
    for r, p in groups:
        block = tables_part[tables_part.index(f"{r} {p}:"):].split("\n\n")[0].splitlines()
        want = ratios.get(f"dense ({r} {p}) / sparse ({r} {p})", ratios.get("dense / sparse"))
        (row,) = [line for line in block if line.startswith("dense / sparse ")]
        assert row.split()[3] == f"{want['to_device']:.2f}x" and row.split()[-1] == f"{want['total']:.2f}x", row
    md = format_table(result, markdown=True)
    assert sum(line.startswith("| model |") for line in md.splitlines()) == 2  # per frame, back to back
    assert "| dense (openvino int8) | " in md


def test_the_exact_sparse_head_on_a_larger_grid_is_the_documented_move(tmp_path) -> None:
    """make reproduce's bench loads the sparse model's 288 x 144 weights under mpchair_sparse_exact.yaml (768 x 512,
    the exact sparse head: the same weights): one plain warning that says both, not 'results may differ'."""
    import warnings

    trained = write_test_config(tmp_path / "trained.yaml", model=dict(backbone="sparse"))
    cfg = load_experiment(trained)
    ckpt = tmp_path / "run.pt"
    model = build_model(cfg.model)
    save_checkpoint(ckpt, Checkpoint.capture(model=model, optimizer=torch.optim.AdamW(model.parameters()), cfg=cfg,
                                             epoch=0, step_in_epoch=0, step=0, global_batch=1))
    exact = load_experiment(write_test_config(tmp_path / "exact.yaml", model=dict(
        backbone="sparse", head="sparse_exact", output_shape=[128, 96])))
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        load_model(exact, ckpt)
    assert [str(w.message) for w in seen] == [
        f"{ckpt}: weights trained on the 96 x 64 grid run on this config's 128 x 96 grid (same pillars, larger area; "
        "anchors at the head map's cell centres; head sparse_exact here (the same weights))"]
