"""KITTI detection AP (OpenPCDet eval.py semantics) on hand-made cases whose numbers
follow from the rules: strict overlap, score thresholds, ignored boxes, DontCare,
difficulties, AOS; Pi3DET's conversion; the score-det command."""

from __future__ import annotations

import json

import numpy as np
import pytest

from omnilidar.cli import main
from omnilidar.errors import InputError
from omnilidar.metrics.kitti_ap import ap_r11, ap_r40, get_thresholds, kitti_eval, pi3det_annos


def anno(boxes, names=None, scores=None, occluded=None, truncated=None, bbox=None):
    """A camera-frame anno of boxes [x, y, z, l, h, w, ry] (bottom centre), image boxes 50 px tall."""
    b = np.asarray(boxes, np.float64).reshape(-1, 7)
    n = len(b)
    out = {"name": np.array(names or ["Car"] * n, dtype=str) if n else np.zeros(0, str),
           "truncated": np.asarray(truncated if truncated is not None else np.zeros(n), np.float64),
           "occluded": np.asarray(occluded if occluded is not None else np.zeros(n), np.float64),
           "bbox": np.asarray(bbox, np.float64).reshape(n, 4) if bbox is not None else
           np.tile([0.0, 0.0, 50.0, 50.0], (n, 1)) + np.arange(n)[:, None] * [60, 0, 60, 0],
           "location": b[:, 0:3], "dimensions": b[:, 3:6], "rotation_y": b[:, 6],
           "alpha": b[:, 6] - np.arctan2(b[:, 0], b[:, 2]) if n else np.zeros(0)}
    if scores is not None:
        out["score"] = np.asarray(scores, np.float64)
    return out


def cars(n, start=0):
    """n separate cars on a line, 10 m apart."""
    return [[-20 + 10 * ((start + k) % 5), 1.6, 10 + 8 * ((start + k) // 5), 4.0, 1.5, 1.7, 0.3 * k] for k in range(n)]


def ap(result, rule, cls, metric, overlap_set=0, difficulty="easy"):
    return result[rule][cls][metric][overlap_set][difficulty]


def test_perfect_detections_with_many_boxes_score_100_everywhere():
    frames = [cars(5, 5 * f) for f in range(10)]  # 50 boxes: the 41 thresholds are all filled
    result = kitti_eval([anno(b) for b in frames], [anno(b, scores=np.linspace(0.9, 0.5, 5)) for b in frames],
                        ["Car"])
    for metric in ("bbox", "bev", "3d", "aos"):
        for rule in ("R11", "R40"):
            assert ap(result, rule, "Car", metric) == pytest.approx(100.0)
    assert result["official"]["Car_3d/moderate_R40"] == pytest.approx(100.0)
    assert len(result["precision"]["Car"]["3d"][0]["easy"]) == 41


def test_few_boxes_truncate_the_curve():
    """The curve is indexed by score thresholds: 4 boxes, 2 perfect detections -> R11 = 1/11."""
    gt = anno(cars(4))
    result = kitti_eval([gt], [anno(cars(2), scores=[0.9, 0.8])], ["Car"])
    assert ap(result, "R11", "Car", "3d") == pytest.approx(100 / 11)
    assert ap(result, "R40", "Car", "3d") == pytest.approx(100 / 40)  # R40 starts at index 1
    assert list(get_thresholds(np.array([0.9, 0.8]), 4)) == [0.9, 0.8]
    # Many matched scores: one threshold per 1/40 of recall.
    assert len(get_thresholds(np.linspace(1, 0.01, 100), 100)) == 41


def test_overlap_must_exceed_the_threshold_strictly():
    """Pedestrian image-box threshold 0.5: IoU exactly 0.5 is no match, 0.51 is one."""
    gt = anno([[0, 1.7, 10, 0.8, 1.7, 0.6, 0]], ["Pedestrian"], bbox=[[0, 0, 100, 50]])
    at = anno([[0, 1.7, 10, 0.8, 1.7, 0.6, 0]], ["Pedestrian"], [0.9], bbox=[[0, 0, 50, 50]])
    above = anno([[0, 1.7, 10, 0.8, 1.7, 0.6, 0]], ["Pedestrian"], [0.9], bbox=[[0, 0, 51, 50]])
    assert ap(kitti_eval([gt], [at], ["Pedestrian"]), "R11", "Pedestrian", "bbox") == 0.0
    assert ap(kitti_eval([gt], [above], ["Pedestrian"]), "R11", "Pedestrian", "bbox") == pytest.approx(100 / 11)


def test_a_duplicate_is_a_false_positive_and_matching_prefers_scores():
    boxes = cars(2)
    dup = anno([boxes[0], boxes[0], boxes[1]], scores=[0.9, 0.8, 0.7])
    # Thresholds 0.9 and 0.7; at 0.7 three detections for two boxes: precision 2/3.
    assert ap(kitti_eval([anno(boxes)], [dup], ["Car"]), "R40", "Car", "3d") == pytest.approx(100 * (2 / 3) / 40)
    # One box, a tight low-scored and a looser high-scored detection: the threshold is the high
    # score (the first pass takes the best score), so precision stays 1 (with the tight one's
    # score as threshold both would count and precision be 1/2).
    shifted = list(boxes[0])
    shifted[0] += 0.3
    two = anno([boxes[0], shifted], scores=[0.6, 0.9])
    assert ap(kitti_eval([anno(boxes[:1])], [two], ["Car"]), "R11", "Car", "3d") == pytest.approx(100 / 11)


def test_dontcare_absorbs_detections_in_the_image_metric_only():
    boxes = cars(2)
    gt = anno(boxes + [[0, 0, 0, -1, -1, -1, -10]], ["Car", "Car", "DontCare"],
              bbox=[[0, 0, 50, 50], [60, 0, 110, 50], [500, 0, 600, 60]])
    dt = anno(boxes + [[20, 1.6, 60, 4, 1.5, 1.7, 0]], scores=[0.9, 0.7, 0.8],
              bbox=[[0, 0, 50, 50], [60, 0, 110, 50], [510, 5, 560, 55]])
    result = kitti_eval([gt], [dt], ["Car"])
    assert ap(result, "R40", "Car", "bbox") == pytest.approx(100 / 40)  # absorbed: no false positive
    assert ap(result, "R40", "Car", "3d") == pytest.approx(100 * (2 / 3) / 40)  # a false positive in 3D


def test_difficulties_and_similar_classes_are_ignored_not_penalised():
    boxes = cars(2)
    # The second car is occluded (level 2): ignored in easy and moderate, counted in hard. Its
    # detection scores highest; where the box is ignored it is neither a hit nor a false positive.
    gt = anno(boxes, occluded=[0, 2])
    dt = anno(boxes, scores=[0.9, 0.95])
    result = kitti_eval([gt], [dt], ["Car"])
    # easy / moderate: one box, one threshold (0.9), precision 1 (a false positive would make it 1/2).
    for difficulty in ("easy", "moderate"):
        assert ap(result, "R11", "Car", "3d", difficulty=difficulty) == pytest.approx(100 / 11)
        assert ap(result, "R40", "Car", "3d", difficulty=difficulty) == 0.0
    assert ap(result, "R40", "Car", "3d", difficulty="hard") == pytest.approx(100 / 40)  # two thresholds
    # A Van detected as Car is ignored for Car; a Cyclist box detected as Car is a false positive.
    for other, expected in (("Van", 100 / 11), ("Cyclist", 100 * (1 / 2) / 11)):
        result = kitti_eval([anno(boxes, ["Car", other])], [anno(boxes, scores=[0.9, 0.95])], ["Car"])
        assert ap(result, "R11", "Car", "3d") == pytest.approx(expected)
    # Image boxes 40 px tall or less are hard-only (min heights 40 / 25 / 25).
    low = anno(boxes, bbox=[[0, 0, 50, 50], [60, 0, 110, 40]])
    result = kitti_eval([low], [anno(boxes, scores=[0.9, 0.95], bbox=[[0, 0, 50, 50], [60, 0, 110, 41]])], ["Car"])
    assert ap(result, "R11", "Car", "3d", difficulty="easy") == pytest.approx(100 / 11)
    assert ap(result, "R40", "Car", "3d", difficulty="easy") == 0.0
    assert ap(result, "R40", "Car", "3d", difficulty="moderate") == pytest.approx(100 / 40)


def test_aos_counts_heading_errors_and_both_overlap_sets_are_reported():
    frames = [cars(5, 5 * f) for f in range(10)]
    flipped = []
    for b in frames:
        d = anno(b, scores=np.linspace(0.9, 0.5, 5))
        d["rotation_y"] = d["rotation_y"] + np.pi  # the same box, heading reversed
        d["alpha"] = d["alpha"] + np.pi
        flipped.append(d)
    result = kitti_eval([anno(b) for b in frames], flipped, ["Car", "Pedestrian"])
    assert ap(result, "R40", "Car", "3d") == pytest.approx(100.0)
    assert ap(result, "R40", "Car", "aos") == pytest.approx(0.0, abs=1e-9)
    assert result["min_overlaps"]["Car"]["3d"] == [0.7, 0.5] and result["min_overlaps"]["Pedestrian"]["bev"] == [0.5, 0.25]
    assert ap(result, "R11", "Pedestrian", "3d", overlap_set=1) == 0.0
    # Detections with alpha -10 switch AOS off, as OpenPCDet.
    for d in flipped:
        d["alpha"] = np.full(len(d["alpha"]), -10.0)
    assert "aos" not in kitti_eval([anno(b) for b in frames], flipped, ["Car"])["R11"]["Car"]


def test_rotated_boxes_match_themselves_exactly():
    """OpenPCDet's numba IoU returns 0 for identical rotated boxes; ours is exact."""
    b = [[3.0, 1.6, 40.0, 4.2, 1.5, 1.8, 0.7853981]]
    result = kitti_eval([anno(b)], [anno(b, scores=[0.5])], ["Car"])
    assert ap(result, "R11", "Car", "3d") == pytest.approx(100 / 11)



def test_sums_run_in_openpcdet_order_to_the_last_bit():
    """AP (over thresholds) and AOS similarity (over matches) are summed term after term as
    OpenPCDet does; numpy's pairwise sum rounds differently (last bits)."""
    prec = np.array([1.0, 1.0, 2 / 3, 3 / 4, 4 / 5, 5 / 7, 6 / 9, 7 / 10, 7 / 11, 8 / 13] + [0.0] * 31)
    assert ap_r40(prec) == 16.373418248418254  # value from OpenPCDet eval.py (get_mAP_R40) on this array
    assert ap_r11(prec) == 22.14876033057851  # value from OpenPCDet eval.py (get_mAP) on this array

    def case(n, n_fp, alpha_step):
        """n cars all found, n_fp false positives far away with interleaved scores, heading errors
        growing by alpha_step per detection (image metric and AOS only: the boxes are identical,
        where OpenPCDet's rotated IoU fails)."""
        boxes = cars(n)
        fps = [[30.0 + 10 * k, 1.6, 60.0, 4.0, 1.5, 1.7, 0.0] for k in range(n_fp)]
        dt = anno(boxes + fps, scores=list(np.linspace(0.95, 0.3, n)) + list(np.linspace(0.9, 0.35, n_fp)))
        dt["alpha"] = dt["alpha"] + alpha_step * np.arange(n + n_fp)
        return kitti_eval([anno(boxes)], [dt], ["Car"])

    result = case(15, 5, 0.05)
    # values from OpenPCDet eval.py on this case
    assert ap(result, "R40", "Car", "bbox") == 27.893413775766724
    assert ap(result, "R40", "Car", "aos") == 27.40593974469811
    result = case(20, 6, 0.13)
    assert ap(result, "R11", "Car", "aos") == 33.30619776777766  # value from OpenPCDet eval.py on this case
    assert ap(result, "R40", "Car", "aos") == 32.066913093492225  # value from OpenPCDet eval.py on this case

def test_pi3det_conversion_makes_every_box_easy():
    lidar = np.array([[10.0, 2.0, -1.0, 4.0, 2.0, 1.5, 0.0], [5.0, -1.0, -0.5, 0.8, 0.6, 1.7, 1.0]])
    a = pi3det_annos(lidar, ["Vehicle", "Pedestrian"], scores=[0.9, 0.4])
    assert list(a["name"]) == ["Car", "Pedestrian"]
    np.testing.assert_allclose(a["location"][0], [-2.0, 1.75, 10.0])  # bottom centre, camera axes
    np.testing.assert_allclose(a["dimensions"][0], [4.0, 1.5, 2.0])  # l, h, w
    assert a["rotation_y"][0] == pytest.approx(-np.pi / 2)
    assert a["alpha"][0] == pytest.approx(-np.arctan2(-2.0, 10.0) - np.pi / 2)
    np.testing.assert_array_equal(a["bbox"], [[0, 0, 50, 50]] * 2)
    result = kitti_eval([pi3det_annos(lidar, ["Vehicle", "Pedestrian"])], [a], ["Car", "Pedestrian"])
    for cls in ("Car", "Pedestrian"):
        values = result["R11"][cls]["3d"][0]
        assert values["easy"] == values["moderate"] == values["hard"] == pytest.approx(100 / 11)
    empty = pi3det_annos(np.zeros((0, 7)), [])
    assert empty["location"].shape == (0, 3) and len(empty["name"]) == 0
    with pytest.raises(InputError, match="2 names for 1 boxes"):
        pi3det_annos(lidar[:1], ["Car", "Car"])


def test_detection_evaluate_scores_lidar_predictions_end_to_end():
    from omnilidar.downstream.det.evaluate import score

    rng = np.random.default_rng(0)
    records, predictions = [], []
    for f in range(10):
        boxes = np.stack([10 + 8 * np.arange(5), rng.uniform(-20, 20, 5), np.full(5, -1.0), np.full(5, 3.9),
                          np.full(5, 1.6), np.full(5, 1.56), rng.uniform(-3, 3, 5)], 1).astype(np.float32)
        records.append({"frame_id": f"{f:06d}", "boxes": boxes, "names": ["Car"] * 5})
        predictions.append({"frame_id": f"{f:06d}", "boxes": boxes[:4], "names": ["Car"] * 4,
                            "scores": np.linspace(0.9, 0.6, 4)})
    per_class = score(records, predictions, ["Car"])["Car"]
    # 40 of 50 boxes found without a false positive: precision 1 at every threshold taken.
    taken = len(get_thresholds(np.concatenate([p["scores"] for p in predictions]), 50))
    assert 30 <= taken < 41 and per_class["3d_R40@0.5"] == pytest.approx(100 * (taken - 1) / 40)
    assert per_class["gt_boxes"] == 50 and per_class["detections"] == 40
    assert len(per_class["precision_3d@0.5"]) == 41


def write_label_file(path, objects):
    path.write_text("".join(
        f"{name} 0.00 0 {alpha:.2f} {b[0]} {b[1]} {b[2]} {b[3]} {h} {w} {l} {x} {y} {z} {ry}"
        + (f" {score}" if score is not None else "") + "\n"
        for name, alpha, b, (h, w, l), (x, y, z), ry, score in objects))


def test_score_det_command_on_label_folders(tmp_path, capsys):
    labels, preds = tmp_path / "label_2", tmp_path / "pred"
    labels.mkdir()
    preds.mkdir()
    car = ("Car", -1.5, (100, 100, 300, 200), (1.5, 1.7, 4.0), (2.0, 1.6, 15.0), 0.1)
    for frame in ("000000", "000001"):
        write_label_file(labels / f"{frame}.txt", [(*car, None)])
        write_label_file(preds / f"{frame}.txt", [(*car, 0.8)])
    out = tmp_path / "ap.json"
    assert main(["score-det", "--predictions", str(preds), "--labels", str(labels), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "Car AP@0.70, 0.70, 0.70:" in printed and "3d   AP:9.0909" in printed and "2 frames" in printed
    doc = json.loads(out.read_text())
    assert doc["classes"] == ["Car"] and doc["R11"]["Car"]["3d"][0]["easy"] == pytest.approx(100 / 11)
    # A frame without predictions, and a prediction without a score: one error line each, no output.
    (preds / "000001.txt").unlink()
    out.unlink()
    assert main(["score-det", "--predictions", str(preds), "--labels", str(labels), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "000001.txt" in err and "needs a prediction file" in err and not out.exists()
    write_label_file(preds / "000001.txt", [(*car, None)])
    assert main(["score-det", "--predictions", str(preds), "--labels", str(labels)]) == 2
    assert "has no score" in capsys.readouterr().err


def test_score_det_command_on_pi3det_infos(tmp_path, capsys):
    from omnilidar.io import pi3det
    from omnilidar.lidar.scan import Boxes

    boxes = np.array([[10, 2, -1, 4, 2, 1.5, 0.2]], np.float32)
    infos = [pi3det.make_info("000000", "Quadruped", "velodyne/000000.bin", Boxes(boxes, ["Vehicle"]))]
    path = tmp_path / "infos.pkl"
    import pickle

    path.write_bytes(pickle.dumps(infos))
    preds = tmp_path / "pred"
    preds.mkdir()
    a = pi3det_annos(boxes, ["Vehicle"])
    l, h, w = a["dimensions"][0]
    write_label_file(preds / "000000.txt", [("Car", a["alpha"][0], (0, 0, 50, 50), (h, w, l),
                                             tuple(a["location"][0]), a["rotation_y"][0], 0.7)])
    assert main(["score-det", "--predictions", str(preds), "--infos", str(path)]) == 0
    assert "3d   AP:9.0909, 9.0909, 9.0909" in capsys.readouterr().out


def test_printout_reads_back_with_openpcdets_layout():
    """A parser written for OpenPCDet's eval.py printout reads ours: per class and overlap set a
    `Car AP@...:` block then a `Car AP_R40@...:` block, bbox/bev/3d with 4 decimals, aos with 2."""
    import re

    frames = [cars(5, 5 * f) for f in range(10)]
    dets = [anno(b, scores=np.linspace(0.9, 0.5, 5)) for b in frames]
    for d in dets[::2]:
        d["location"] = d["location"] + [0.3, 0.0, 0.4]  # some boxes off: values differ between metrics
    result = kitti_eval([anno(b) for b in frames], dets, ["Car"])
    header = re.compile(r"^(\w+) (AP|AP_R40)@(\d\.\d\d), (\d\.\d\d), (\d\.\d\d):$")
    value = {m: re.compile(rf"^{re.escape(label)}:(\d+\.\d{{{d}}}), (\d+\.\d{{{d}}}), (\d+\.\d{{{d}}})$")
             for m, label, d in (("bbox", "bbox AP", 4), ("bev", "bev  AP", 4), ("3d", "3d   AP", 4), ("aos", "aos  AP", 2))}
    lines = result["result_str"].splitlines()
    assert len(lines) == 2 * 2 * 5  # 2 overlap sets x (R11, R40) x (header + 4 metrics)
    for block in range(4):
        head = header.match(lines[5 * block])
        assert head and head.group(1) == "Car" and head.group(2) == ("AP" if block % 2 == 0 else "AP_R40"), lines[5 * block]
        s, rule = block // 2, ("R11", "R40")[block % 2]
        assert float(head.group(5)) == result["min_overlaps"]["Car"]["3d"][s]
        for k, metric in enumerate(("bbox", "bev", "3d", "aos")):
            m = value[metric].match(lines[5 * block + 1 + k])
            assert m, lines[5 * block + 1 + k]
            digits = 2 if metric == "aos" else 4
            for diff, text in zip(("easy", "moderate", "hard"), m.groups()):
                assert text == f"{ap(result, rule, 'Car', metric, s, diff):.{digits}f}"
