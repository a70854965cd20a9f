"""The KITTI evaluator (detector.eval) on hand-computed cases, and ``detector eval`` on files."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from detector.cli import main
from detector.eval import evaluate, evaluate_folders, format_table, get_thresholds
from mpchair.core.errors import InputError
from mpchair.kitti import Labels, read_labels, write_imageset, write_labels


def obj(name="Car", i=0, *, height=50.0, occ=0, trunc=0.0, alpha=0.3, ry=0.6, dx=0.0, score=None, left=None,
        loc=None, hwl=(1.5, 1.6, 3.9)):
    """One object row: slot ``i`` puts it at its own place in the image (30 px apart) and in 3D (8 m apart)."""
    x = 30.0 * i if left is None else left
    return dict(name=name, trunc=trunc, occ=occ, alpha=alpha, bbox=(x, 100.0, x + 20.0, 100.0 + height),
                hwl=hwl, loc=(8.0 * i + dx, 1.6, 20.0) if loc is None else loc, ry=ry, score=score)


def labels(rows: list[dict], scored: bool = False) -> Labels:
    if not rows:
        return Labels.empty(with_score=scored)
    return Labels(
        names=[r["name"] for r in rows], truncated=[r["trunc"] for r in rows], occluded=[r["occ"] for r in rows],
        alpha=[r["alpha"] for r in rows], bbox=[r["bbox"] for r in rows], dims_hwl=[r["hwl"] for r in rows],
        location=[r["loc"] for r in rows], rotation_y=[r["ry"] for r in rows],
        score=[r["score"] for r in rows] if scored else None,
    )


def as_detections(rows: list[dict], scores=None) -> Labels:
    """The GT rows themselves as detections (identical boxes, rotated), scores descending unless given."""
    out = []
    for k, r in enumerate(rows):
        out.append({**r, "score": (1.0 - 0.001 * k) if scores is None else scores[k]})
    return labels(out, scored=True)


def ap(result, cls, metric, variant):
    return result.ap[cls][metric][variant]


ALL = [("bbox", "R11"), ("bbox", "R40"), ("bev", "R11"), ("bev", "R40"), ("3d", "R11"), ("3d", "R40"),
       ("aos", "R11"), ("aos", "R40")]


def test_perfect_detections_on_45_gt_score_exactly_100():
    rng = np.random.default_rng(0)
    gt_frames = [[obj("Car", i, ry=float(rng.uniform(-3, 3)), alpha=float(rng.uniform(-3, 3))) for i in range(15)]
                 for _ in range(3)]
    gt = [labels(f) for f in gt_frames]
    dt = [as_detections(f) for f in gt_frames]
    result = evaluate(gt, dt, ["Car"])
    assert result.num_gt["Car"] == (45, 45, 45)
    assert result.aos_computed
    for metric, variant in ALL:
        assert ap(result, "Car", metric, variant) == (100.0, 100.0, 100.0), (metric, variant)
    assert result.warnings == ()
    assert result.to_json_dict()["Car"]["3d"]["R40"] == [100.0, 100.0, 100.0]


@pytest.mark.parametrize(("n", "r40", "r11"), [(1, 0.0, 100 / 11), (2, 2.5, 100 / 11), (10, 22.5, 300 / 11),
                                               (20, 47.5, 500 / 11), (40, 97.5, 1000 / 11), (41, 100.0, 100.0)])
def test_few_gt_saturation(n, r40, r11):
    rows = [obj("Chair", i, ry=1.1, hwl=(0.9, 0.5, 0.5)) for i in range(n)]
    result = evaluate([labels(rows)], [as_detections(rows)], ["Chair"])
    assert result.num_gt["Chair"] == (n, n, n)
    for metric in ("bbox", "bev", "3d"):
        assert ap(result, "Chair", metric, "R40") == pytest.approx((r40,) * 3, abs=1e-12)
        assert ap(result, "Chair", metric, "R11") == pytest.approx((r11,) * 3, abs=1e-12)
    assert (len(result.warnings) > 0) == (n < 41)


def test_no_valid_gt_gives_zero_without_error():
    gt = [labels([obj("Car", 0)])]
    dt = [as_detections([obj("Chair", 1)])]
    result = evaluate(gt, dt, ["Chair"])
    assert result.num_gt["Chair"] == (0, 0, 0)
    assert ap(result, "Chair", "3d", "R40") == (0.0, 0.0, 0.0)
    assert any("0 valid GT" in w for w in result.warnings)


def test_known_pr_curve():
    # 80 valid GT, one per frame; 40 of them detected exactly (TP), plus 20 far-away FPs ranked TP, TP, FP, ...
    # get_thresholds with K = 40 TP scores and num_gt = 80 takes TP number i when (i+2)/80 - r* >= r* - (i+1)/80,
    # r* += 1/40 per take: i = 0, 1, then every odd i (3, 5, ..., 39) -> 21 thresholds.
    n_gt, n_tp = 80, 40
    gt_rows = [[obj("Chair", 0, ry=0.9, hwl=(0.9, 0.5, 0.6))] for _ in range(n_gt)]
    ranking = []  # (is_tp, score) in descending score
    tp_seen = 0
    while tp_seen < n_tp:
        for kind in (True, True, False):
            ranking.append(kind)
            tp_seen += kind
    scores = np.linspace(0.99, 0.1, len(ranking))
    dt_rows: list[list[dict]] = [[] for _ in range(n_gt)]
    k_tp = k_fp = 0
    tp_scores = []
    for is_tp, s in zip(ranking, scores):
        if is_tp:
            dt_rows[k_tp].append({**gt_rows[k_tp][0], "score": float(s)})
            tp_scores.append(float(s))
            k_tp += 1
        else:  # an FP in a frame of its own GT, far from it in 2D and 3D
            dt_rows[k_fp].append({**obj("Chair", 5, hwl=(0.9, 0.5, 0.6)), "score": float(s)})
            k_fp += 1
    gt = [labels(r) for r in gt_rows]
    dt = [labels(r, scored=True) for r in dt_rows]
    result = evaluate(gt, dt, ["Chair"])
    assert result.num_gt["Chair"] == (80, 80, 80)

    picked = [0, 1] + list(range(3, 40, 2))
    np.testing.assert_array_equal(get_thresholds(np.array(tp_scores), n_gt), np.array(tp_scores)[picked])
    # at TP number i: i + 1 TPs and i // 2 FPs score at least as high
    precision = [(i + 1) / (i + 1 + i // 2) for i in picked] + [0.0] * (41 - len(picked))
    assert precision[:4] == [1.0, 1.0, 0.8, 0.75]  # non-increasing, so max-accumulation changes nothing
    r40 = 100 * sum(precision[1:]) / 40
    r11 = 100 * sum(precision[0::4]) / 11
    assert r40 == pytest.approx(35.734649, abs=1e-6) and r11 == pytest.approx(40.613240, abs=1e-6)
    for metric in ("bbox", "bev", "3d", "aos"):
        assert ap(result, "Chair", metric, "R40") == pytest.approx((r40,) * 3, abs=1e-9)
        assert ap(result, "Chair", metric, "R11") == pytest.approx((r11,) * 3, abs=1e-9)


def test_aos_similarity_and_off_switch():
    rows = [obj("Car", i, alpha=0.2) for i in range(41)]
    det = as_detections([{**r, "alpha": 0.2 - math.pi / 3} for r in rows])
    result = evaluate([labels(rows)], [det], ["Car"])
    assert ap(result, "Car", "aos", "R40") == pytest.approx((75.0,) * 3, abs=1e-9)  # (1 + cos 60deg) / 2
    assert ap(result, "Car", "3d", "R40") == (100.0,) * 3
    off = as_detections([{**r, "alpha": -10.0 if i == 7 else r["alpha"]} for i, r in enumerate(rows)])
    result = evaluate([labels(rows)], [off], ["Car"])
    assert not result.aos_computed and "aos" not in result.ap["Car"]
    assert result.to_json_dict()["Car"]["aos"] is None
    assert ap(result, "Car", "bbox", "R40") == (100.0,) * 3


def _with_top_fp(extra: dict, gt_extra: list[dict] | None = None):
    """41 perfect Car detections plus one extra detection scored above all of them."""
    rows = [obj("Car", i) for i in range(41)]
    gt = labels(rows + (gt_extra or []))
    dt = labels([{**extra, "score": 2.0}] + [{**r, "score": 1.0 - 0.001 * k} for k, r in enumerate(rows)],
                scored=True)
    return evaluate([gt], [dt], ["Car"])


FP_AP = 100 * 41 / 42  # one FP above 41 TPs: precision k/(k+1) rising to 41/42, max-accumulated everywhere


def test_plain_false_positive_costs_precision():
    result = _with_top_fp(obj("Car", 50))
    for metric, variant in ALL[:6]:
        assert ap(result, "Car", metric, variant) == pytest.approx((FP_AP,) * 3, abs=1e-9)


def test_dontcare_suppresses_false_positives_in_2d_only():
    dontcare = {**obj("DontCare", 0, left=2000.0, height=200.0), "bbox": (2000.0, 50.0, 2200.0, 300.0)}
    inside = {**obj("Car", 50), "bbox": (2050.0, 100.0, 2070.0, 150.0)}  # 2D box fully inside the DontCare box
    result = _with_top_fp(inside, [dontcare])
    assert ap(result, "Car", "bbox", "R40") == (100.0,) * 3
    assert ap(result, "Car", "bbox", "R11") == (100.0,) * 3
    for metric in ("bev", "3d"):
        assert ap(result, "Car", metric, "R40") == pytest.approx((FP_AP,) * 3, abs=1e-9)
    # criterion: intersection / area(detection) > 0.7 (Car's 2D threshold)
    partial = {**inside, "bbox": (1988.0, 100.0, 2008.0, 150.0)}  # 8 of 20 px wide inside: 40 %
    result = _with_top_fp(partial, [dontcare])
    assert ap(result, "Car", "bbox", "R40") == pytest.approx((FP_AP,) * 3, abs=1e-9)


def test_neighbour_class_and_other_class():
    van = obj("Van", 60)
    result = _with_top_fp({**van, "name": "Car"}, [van])  # a Car detection on a Van: neither TP nor FP
    assert ap(result, "Car", "3d", "R40") == (100.0,) * 3
    assert result.num_gt["Car"] == (41, 41, 41)  # the Van is no GT of Car (no FN when missed)
    truck = obj("Truck", 60)
    result = _with_top_fp({**truck, "name": "Car"}, [truck])  # not a neighbour: an FP
    assert ap(result, "Car", "3d", "R40") == pytest.approx((FP_AP,) * 3, abs=1e-9)
    # Person_sitting is Pedestrian's neighbour; names compare case-insensitively on both sides
    peds = [obj("pedestrian", i, hwl=(1.7, 0.6, 0.8)) for i in range(41)]
    sit = obj("Person_sitting", 60, hwl=(1.2, 0.6, 0.8))
    dt = as_detections([{**sit, "name": "PEDESTRIAN"}] + [{**r, "name": "Pedestrian"} for r in peds])
    result = evaluate([labels(peds + [sit])], [dt], ["Pedestrian"])
    assert ap(result, "Pedestrian", "bev", "R40") == (100.0,) * 3


def test_difficulty_boundaries():
    rows = [
        obj("Car", 0, height=40.0),  # <= 40: not Easy; Moderate/Hard valid
        obj("Car", 1, height=40.01),  # valid everywhere
        obj("Car", 2, height=25.0),  # ignored everywhere (<= 25)
        obj("Car", 3, occ=1),  # Moderate/Hard
        obj("Car", 4, occ=2),  # Hard only
        obj("Car", 5, occ=3),  # unknown occlusion: ignored everywhere
        obj("Car", 6, trunc=0.15),  # at the Easy limit: valid everywhere
        obj("Car", 7, trunc=0.16),  # Moderate/Hard
        obj("Car", 8, trunc=0.3),  # Moderate/Hard
        obj("Car", 9, trunc=0.5),  # Hard
        obj("Car", 10, trunc=0.51),  # ignored everywhere
    ]
    result = evaluate([labels(rows)], [Labels.empty(with_score=True)], ["Car"])
    assert result.num_gt["Car"] == (2, 6, 8)


def test_detections_on_ignored_gt_and_small_detections_are_not_false_positives():
    easy = [obj("Car", i) for i in range(41)]
    hard_only = [obj("Car", 41 + i, occ=2) for i in range(5)]  # ignored at Easy and Moderate
    small_fp = {**obj("Car", 80, height=24.0), "score": 3.0}  # unmatched, 24 px: ignored at every level
    gt = labels(easy + hard_only)
    dt = labels([small_fp] + [{**r, "score": 1.0 - 0.001 * k} for k, r in enumerate(easy + hard_only)], scored=True)
    result = evaluate([gt], [dt], ["Car"])
    assert result.num_gt["Car"] == (41, 41, 46)
    for metric, variant in ALL:
        assert ap(result, "Car", metric, variant) == (100.0,) * 3
    # a 25 px unmatched detection is ignored at Easy (< 40) but an FP at Moderate/Hard (25 is not < 25)
    fp25 = {**obj("Car", 80, height=25.0), "score": 3.0}
    dt = labels([fp25] + [{**r, "score": 1.0 - 0.001 * k} for k, r in enumerate(easy + hard_only)], scored=True)
    result = evaluate([gt], [dt], ["Car"])
    bev = ap(result, "Car", "bev", "R40")
    assert bev[0] == 100.0
    assert bev[1] == pytest.approx(FP_AP, abs=1e-9)
    assert bev[2] == pytest.approx(100 * 46 / 47, abs=1e-9)


def test_overall_level_counts_every_box_and_ignores_no_detection():
    """``overall``: the occluded, truncated and tiny GT of the class are valid, and a small detection is an FP."""
    easy = [obj("Car", i) for i in range(41)]
    others = [obj("Car", 41, occ=2), obj("Car", 42, occ=3), obj("Car", 43, trunc=0.9), obj("Car", 44, height=10.0),
              obj("Car", 45, height=25.0)]
    van = obj("Van", 46)  # a neighbour stays ignored: a Car detection on it is neither TP nor FP
    gt = labels(easy + others + [van])
    tps = [{**r, "score": 1.0 - 0.001 * k} for k, r in enumerate(easy + others)]
    result = evaluate([gt], [labels(tps + [{**van, "name": "Car", "score": 0.5}], scored=True)], ["Car"])
    assert result.num_gt["Car"] == (41, 41, 42) and result.num_gt_overall["Car"] == 46
    for metric, variant in ALL:
        assert result.overall["Car"][metric][variant] == 100.0, (metric, variant)
    small_fp = {**obj("Car", 80, height=24.0), "score": 3.0}  # unmatched, 24 px: ignored at every KITTI difficulty
    result = evaluate([gt], [labels([small_fp] + tps, scored=True)], ["Car"])
    assert ap(result, "Car", "3d", "R40") == (100.0,) * 3  # the other Cars only absorb their detections there
    for metric, variant in ALL:  # one FP above 46 TPs: precision 46/47 in every slot
        assert result.overall["Car"][metric][variant] == pytest.approx(100 * 46 / 47, abs=1e-9), (metric, variant)
    assert result.precision["Car"]["bev"].shape == (4, 41)


def test_iou_must_be_strictly_greater_than_threshold():
    # Chair BEV/3D threshold 0.5: a detection shifted by l/3 along its length has BEV IoU exactly 0.5 -> no match.
    # ry = -pi/2 puts l along camera z and makes the sensor-style yaw exactly 0, so every corner is exact.
    rows = [obj("Chair", i, ry=-math.pi / 2, hwl=(1.0, 1.0, 3.0)) for i in range(41)]
    shifted = as_detections([{**r, "loc": (r["loc"][0], r["loc"][1], r["loc"][2] + 1.0)} for r in rows])
    result = evaluate([labels(rows)], [shifted], ["Chair"])
    assert ap(result, "Chair", "bbox", "R40") == (100.0,) * 3
    assert ap(result, "Chair", "bev", "R40") == (0.0,) * 3
    result = evaluate([labels(rows)], [shifted], ["Chair"], min_overlaps={"Chair": (0.5, 0.49, 0.49)})
    assert ap(result, "Chair", "bev", "R40") == (100.0,) * 3


def test_bad_arguments():
    with pytest.raises(ValueError, match="frames"):
        evaluate([Labels.empty()], [], ["Car"])
    with pytest.raises(ValueError, match="no IoU thresholds"):
        evaluate([Labels.empty()], [Labels.empty(with_score=True)], ["Sofa"])
    with pytest.raises(ValueError, match="no scores"):
        evaluate([labels([obj()])], [labels([obj()])], ["Car"])


# --- files and CLI -------------------------------------------------------------------------------------------------


def _write_dataset(tmp_path, n_frames=3, per_frame=15):
    label_dir, result_dir = tmp_path / "label_2", tmp_path / "results"
    ids = [f"{i:06d}" for i in range(n_frames)]
    for k, fid in enumerate(ids):
        rows = [obj("Chair", i, ry=0.37 * (i + k), alpha=0.1 * i, hwl=(0.9, 0.55, 0.6)) for i in range(per_frame)]
        rows.append({**obj("DontCare", 0, left=900.0), "hwl": (-1, -1, -1), "loc": (-1000, -1000, -1000)})
        write_labels(label_dir / f"{fid}.txt", labels(rows))
        gt = read_labels(label_dir / f"{fid}.txt").objects()  # detections = GT as written (2 decimals)
        write_labels(result_dir / f"{fid}.txt", dataclasses.replace(gt, score=np.linspace(1, 0.5, len(gt))))
    write_imageset(tmp_path / "val.txt", ids)
    return label_dir, result_dir, ids


def test_evaluate_folders_round_trip(tmp_path):
    label_dir, result_dir, ids = _write_dataset(tmp_path)
    result = evaluate_folders(label_dir, result_dir, ids, ["chair"])
    assert result.num_gt["chair"] == (45, 45, 45)
    assert ap(result, "chair", "3d", "R40") == (100.0,) * 3
    assert "chair" in format_table(result)
    (result_dir / "000001.txt").write_text(
        "Chair -1 -1 0.1 0 100 20 150 0.9 0.55 0.6 0 1.6 20 0.0\n")  # 15 columns: no score
    with pytest.raises(InputError, match="16th column"):
        evaluate_folders(label_dir, result_dir, ids, ["Chair"])


def test_cli_json_and_errors(tmp_path, capsys):
    label_dir, result_dir, _ = _write_dataset(tmp_path)
    args = ["eval", "--labels", str(label_dir), "--results", str(result_dir), "--split", str(tmp_path / "val.txt"),
            "--classes", "Chair,Car", "--json"]
    with pytest.raises(SystemExit) as e:
        main(args)
    assert e.value.code == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {"Chair", "Car", "num_gt", "num_gt_overall"}
    assert out["num_gt"] == {"Chair": [45, 45, 45], "Car": [0, 0, 0]}
    assert out["num_gt_overall"] == {"Chair": 45, "Car": 0}
    for metric in ("bbox", "bev", "3d", "aos"):
        assert out["Chair"][metric] == {"R11": [100.0] * 3, "R40": [100.0] * 3,
                                        "overall": {"R11": 100.0, "R40": 100.0}}
        assert out["Car"][metric] == {"R11": [0.0] * 3, "R40": [0.0] * 3, "overall": {"R11": 0.0, "R40": 0.0}}

    with pytest.raises(SystemExit) as e:
        main(args[:-1])  # the table
    assert e.value.code == 0
    table = capsys.readouterr().out
    assert "Chair" in table and "AP_R40" in table and "100.00" in table
    header = next(line for line in table.splitlines() if line.startswith("Chair"))
    assert header.split()[-4:] == ["Easy", "Moderate", "Hard", "Overall"]
    assert next(line for line in table.splitlines() if "num_gt" in line).split()[-4:] == ["45"] * 4

    (result_dir / "000002.txt").unlink()
    with pytest.raises(SystemExit) as e:
        main(args)
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "000002.txt" in err and "missing" in err


# --- a literal, frame-by-frame transcription of the reference loops, against the flattened numba path -----------


def _literal_ap(gt: list[Labels], dt: list[Labels], cls: str, d: int, thr: float) -> tuple[np.ndarray, np.ndarray]:
    """Max-accumulated (precision, aos) (41,) for the 2D metric, written as plainly as the reference's loops."""
    from detector.eval.kitti import MAX_OCCLUSION, MAX_TRUNCATION, MIN_HEIGHT

    def iou(a, b, own_area=False):
        iw = min(a[2], b[2]) - max(a[0], b[0])
        ih = min(a[3], b[3]) - max(a[1], b[1])
        if iw <= 0 or ih <= 0:
            return 0.0
        area_a = (a[2] - a[0]) * (a[3] - a[1])
        return iw * ih / (area_a if own_area else area_a + (b[2] - b[0]) * (b[3] - b[1]) - iw * ih)

    frames = []
    n_valid = 0
    for g, t in zip(gt, dt):
        gf = []
        for k in range(len(g)):
            name = g.names[k].lower()
            h = g.bbox[k, 3] - g.bbox[k, 1]
            fail = g.occluded[k] > MAX_OCCLUSION[d] or g.truncated[k] > MAX_TRUNCATION[d] or h <= MIN_HEIGHT[d]
            neighbour = (cls == "car" and name == "van") or (cls == "pedestrian" and name == "person_sitting")
            gf.append(0 if name == cls and not fail else 1 if neighbour or name == cls else -1)
        n_valid += gf.count(0)
        df = [1 if abs(t.bbox[k, 3] - t.bbox[k, 1]) < MIN_HEIGHT[d] else 0 if t.names[k].lower() == cls else -1
              for k in range(len(t))]
        dc = [g.bbox[k] for k in range(len(g)) if g.names[k] == "DontCare"]
        frames.append((g, t, gf, df, dc))

    def stats(g, t, gf, df, dc, cut, score_pass):
        assigned = [False] * len(t)
        tp, fp, sim, scores = 0, 0, 0.0, []
        for i in range(len(g)):
            if gf[i] == -1:
                continue
            best, best_key, ignored_pick = -1, -1e7 if score_pass else 0.0, False
            for j in range(len(t)):
                if df[j] == -1 or assigned[j] or (not score_pass and t.score[j] < cut):
                    continue
                o = iou(t.bbox[j], g.bbox[i])
                if o <= thr:
                    continue
                if score_pass:
                    if t.score[j] > best_key:
                        best, best_key = j, t.score[j]
                elif df[j] == 0 and (o > best_key or ignored_pick):
                    best, best_key, ignored_pick = j, o, False
                elif df[j] == 1 and best == -1:
                    best, ignored_pick = j, True
            if best == -1:
                continue
            assigned[best] = True
            if gf[i] == 0 and df[best] == 0:
                tp += 1
                scores.append(t.score[best])
                sim += (1 + math.cos(g.alpha[i] - t.alpha[best])) / 2
        fp = sum(1 for j in range(len(t)) if not assigned[j] and df[j] == 0 and t.score[j] >= cut)
        for box in dc:
            for j in range(len(t)):
                if not assigned[j] and df[j] == 0 and t.score[j] >= cut and iou(t.bbox[j], box, True) > thr:
                    assigned[j] = True
                    fp -= 1
        return tp, fp, sim, scores

    tp_scores = [s for f in frames for s in stats(*f, 0.0, True)[3]]
    cuts = get_thresholds(np.array(tp_scores, dtype=np.float64), n_valid) if n_valid else []
    prec, aos = np.zeros(41), np.zeros(41)
    for k, cut in enumerate(cuts):
        tp = fp = 0
        sim = 0.0
        for f in frames:
            a, b, s, _ = stats(*f, cut, False)
            tp, fp, sim = tp + a, fp + b, sim + s
        prec[k], aos[k] = tp / (tp + fp), sim / (tp + fp)
    return np.maximum.accumulate(prec[::-1])[::-1], np.maximum.accumulate(aos[::-1])[::-1]


def test_flattened_matching_equals_literal_loops():
    rng = np.random.default_rng(42)
    names = ["Car", "Van", "Pedestrian", "Person_sitting", "Cyclist", "DontCare"]
    gt, dt = [], []
    for _ in range(40):
        rows = []
        for _ in range(int(rng.integers(0, 9))):
            x, y, h = rng.uniform(0, 300), rng.uniform(0, 100), rng.uniform(15, 90)
            rows.append({**obj(str(rng.choice(names)), 0, occ=int(rng.integers(0, 4)),
                               trunc=float(rng.choice([0.0, 0.15, 0.3, 0.5, 0.6])), alpha=float(rng.uniform(-3, 3))),
                         "bbox": (x, y, x + rng.uniform(20, 80), y + h)})
        rows.sort(key=lambda r: r["name"] == "DontCare")
        dets = []
        for r in rows:  # noisy copies of most objects, plus clutter
            if r["name"] != "DontCare" and rng.uniform() < 0.8:
                dets.append({**r, "bbox": tuple(np.add(r["bbox"], rng.normal(0, 6, 4))),
                             "alpha": r["alpha"] + rng.normal(0, 0.5), "score": float(rng.uniform())})
        for _ in range(int(rng.integers(0, 4))):
            x, y = rng.uniform(0, 300), rng.uniform(0, 100)
            dets.append({**obj(str(rng.choice(names[:5])), 0), "bbox": (x, y, x + 40, y + rng.uniform(10, 80)),
                         "score": float(np.round(rng.uniform(), 1))})  # rounded: score ties
        gt.append(labels(rows))
        dt.append(labels(dets, scored=True))
    result = evaluate(gt, dt, ["Car", "Pedestrian", "Cyclist"])
    assert result.aos_computed
    for cls in ("Car", "Pedestrian", "Cyclist"):
        for d in range(3):
            prec, aos = _literal_ap(gt, dt, cls.lower(), d, 0.7 if cls == "Car" else 0.5)
            assert 0 < prec.max()
            np.testing.assert_allclose(result.precision[cls]["bbox"][d], prec, rtol=0, atol=1e-12)
            np.testing.assert_allclose(result.precision[cls]["aos"][d], aos, rtol=0, atol=1e-12)


def _mixed_frames(seed: int, n_frames: int = 30):
    """Frames whose levels differ: Car / Van / Pedestrian / Person_sitting / Cyclist / DontCare of every height
    (8-90 px), occlusion 0-3 and truncation 0-0.9, scattered in 3D; noisy detections of most objects (some pushed
    below 25 px), plus clutter of every class."""
    rng = np.random.default_rng(seed)
    names = ["Car", "Van", "Pedestrian", "Person_sitting", "Cyclist", "DontCare"]
    gt, dt = [], []
    for _ in range(n_frames):
        rows = []
        for _ in range(int(rng.integers(0, 10))):
            x, y, h = rng.uniform(0, 300), rng.uniform(0, 100), rng.uniform(8, 90)
            name = str(rng.choice(names))
            rows.append({**obj(name, 0, occ=int(rng.integers(0, 4)), trunc=float(rng.choice([0, 0.1, 0.3, 0.5, 0.9])),
                               alpha=float(rng.uniform(-3, 3)), ry=float(rng.uniform(-3, 3)),
                               hwl=(1.5, 1.6, 3.9) if name in ("Car", "Van") else (1.7, 0.6, 0.8),
                               loc=(rng.uniform(-15, 15), 1.6, rng.uniform(5, 40))),
                         "bbox": (x, y, x + rng.uniform(20, 80), y + h)})
        rows.sort(key=lambda r: r["name"] == "DontCare")
        dets = []
        for r in rows:
            if r["name"] != "DontCare" and rng.uniform() < 0.8:
                b = np.add(r["bbox"], rng.normal(0, 4, 4))
                if rng.uniform() < 0.15:
                    b[3] = b[1] + rng.uniform(5, 24)  # a small detection: ignored at the KITTI levels
                dets.append({**r, "bbox": tuple(b), "loc": tuple(np.add(r["loc"], rng.normal(0, 0.3, 3))),
                             "ry": r["ry"] + rng.normal(0, 0.2), "alpha": r["alpha"] + rng.normal(0, 0.3),
                             "score": float(rng.uniform())})
        for _ in range(int(rng.integers(0, 4))):
            x, y = rng.uniform(0, 300), rng.uniform(0, 100)
            dets.append({**obj(str(rng.choice(names[:5])), 0, loc=(rng.uniform(-15, 15), 1.6, rng.uniform(5, 40))),
                         "bbox": (x, y, x + 40, y + rng.uniform(6, 80)), "score": float(np.round(rng.uniform(), 1))})
        gt.append(labels(rows))
        dt.append(labels(dets, scored=True))
    return gt, dt


def _all_easy(frame: Labels, scale: float) -> Labels:
    """The frame with every object Easy: occlusion 0, truncation 0 and 2D boxes stretched vertically by a power of two
    (IoUs and DontCare ratios unchanged bit for bit, every height above 40 px)."""
    bbox = frame.bbox * np.array([1.0, scale, 1.0, scale])
    return dataclasses.replace(frame, bbox=bbox, occluded=np.zeros(len(frame), dtype=np.int64),
                               truncated=np.zeros(len(frame)))


def test_overall_equals_easy_of_the_same_files_with_every_object_easy():
    gt, dt = _mixed_frames(7)
    classes = ["Car", "Pedestrian", "Cyclist"]
    result = evaluate(gt, dt, classes)
    scale = 16.0
    easy_gt, easy_dt = [_all_easy(f, scale) for f in gt], [_all_easy(f, scale) for f in dt]
    heights = np.concatenate([f.bbox[:, 3] - f.bbox[:, 1] for f in easy_gt + easy_dt])
    assert heights.min() > 40  # every GT and every detection passes Easy's 2D-height rule
    rewritten = evaluate(easy_gt, easy_dt, classes)
    assert result.aos_computed and rewritten.aos_computed
    for cls in classes:
        n_class = sum(int(np.count_nonzero(np.char.lower(f.names) == cls.lower())) for f in gt)
        assert result.num_gt_overall[cls] == rewritten.num_gt[cls][0] == n_class
        assert result.num_gt[cls][2] < n_class  # the levels really differ on this data
        for metric in ("bbox", "bev", "3d", "aos"):
            np.testing.assert_array_equal(result.precision[cls][metric][3], rewritten.precision[cls][metric][0])
            for variant in ("R11", "R40"):
                assert result.overall[cls][metric][variant] == rewritten.ap[cls][metric][variant][0]
    assert any(result.overall[c]["3d"]["R40"] != ap(result, c, "3d", "R40")[2] for c in classes)
    assert any(result.overall[c]["bbox"]["R40"] != ap(result, c, "bbox", "R40")[2] for c in classes)
    assert all(result.overall[c]["bev"]["R40"] > 0 for c in classes)
