"""Voxel R-CNN in OpenPCDet's layout: strict loading of OpenPCDet-shaped state
dicts, training and inference on a tiny synthetic scene, the optimiser."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import pytest
import torch
import yaml

from omnilidar.dicts import deep_merge
from omnilidar.downstream.det.models.detector import build_detector
from omnilidar.downstream.det.models.anchor_generator import generate_anchors
from omnilidar.downstream.det.models.box_coder import ResidualCoder
from omnilidar.downstream.det.optim import adam_onecycle, build_optimizer, clip_gradients
from omnilidar.errors import InputError

DOC = yaml.safe_load((Path(__file__).parent.parent / "config" / "detectors" / "voxel_rcnn.yaml").read_text())


CONFIGS = {"paper": DOC["MODEL"], "small": deep_merge(DOC["MODEL"], DOC["CPU_SMALL"])}
KITTI_RANGE = [0.0, -40.0, -3.0, 70.4, 40.0, 1.0]
KITTI_VOXEL = [0.05, 0.05, 0.1]
# Tiny scene: 32 x 32 x 40 voxels, a 4 x 4 BEV map at stride 8.
TINY_RANGE = [0.0, -3.2, -2.0, 6.4, 3.2, 2.0]
TINY_VOXEL = [0.2, 0.2, 0.1]


def _bn(prefix: str, c: int) -> dict:
    return {f"{prefix}.weight": (c,), f"{prefix}.bias": (c,), f"{prefix}.running_mean": (c,),
            f"{prefix}.running_var": (c,), f"{prefix}.num_batches_tracked": ()}


def _openpcdet_voxel_rcnn_car() -> dict:
    """Key -> shape of OpenPCDet's VoxelRCNN state dict for kitti_models/voxel_rcnn_car.yaml,
    written from OpenPCDet's modules (spconv 2 weights: out, kz, ky, kx, in)."""
    t = {"global_step": (1,)}
    b3 = "backbone_3d"
    t[f"{b3}.conv_input.0.weight"] = (16, 3, 3, 3, 4)
    t.update(_bn(f"{b3}.conv_input.1", 16))
    t[f"{b3}.conv1.0.0.weight"] = (16, 3, 3, 3, 16)
    t.update(_bn(f"{b3}.conv1.0.1", 16))
    for stage, cin, cout in (("conv2", 16, 32), ("conv3", 32, 64), ("conv4", 64, 64)):
        t[f"{b3}.{stage}.0.0.weight"] = (cout, 3, 3, 3, cin)
        t[f"{b3}.{stage}.1.0.weight"] = (cout, 3, 3, 3, cout)
        t[f"{b3}.{stage}.2.0.weight"] = (cout, 3, 3, 3, cout)
        for i in range(3):
            t.update(_bn(f"{b3}.{stage}.{i}.1", cout))
    t[f"{b3}.conv_out.0.weight"] = (128, 3, 1, 1, 64)
    t.update(_bn(f"{b3}.conv_out.1", 128))
    b2 = "backbone_2d"
    t[f"{b2}.blocks.0.1.weight"] = (64, 256, 3, 3)
    t.update(_bn(f"{b2}.blocks.0.2", 64))
    t[f"{b2}.blocks.1.1.weight"] = (128, 64, 3, 3)
    t.update(_bn(f"{b2}.blocks.1.2", 128))
    for block, c in ((0, 64), (1, 128)):
        for conv in (4, 7, 10, 13, 16):
            t[f"{b2}.blocks.{block}.{conv}.weight"] = (c, c, 3, 3)
            t.update(_bn(f"{b2}.blocks.{block}.{conv + 1}", c))
    t[f"{b2}.deblocks.0.0.weight"] = (64, 128, 1, 1)
    t.update(_bn(f"{b2}.deblocks.0.1", 128))
    t[f"{b2}.deblocks.1.0.weight"] = (128, 128, 2, 2)
    t.update(_bn(f"{b2}.deblocks.1.1", 128))
    dh = "dense_head"
    t.update({f"{dh}.conv_cls.weight": (2, 256, 1, 1), f"{dh}.conv_cls.bias": (2,),
              f"{dh}.conv_box.weight": (14, 256, 1, 1), f"{dh}.conv_box.bias": (14,),
              f"{dh}.conv_dir_cls.weight": (4, 256, 1, 1), f"{dh}.conv_dir_cls.bias": (4,)})
    rh = "roi_head"
    for layer, c_src in ((0, 32), (1, 64), (2, 64)):
        p = f"{rh}.roi_grid_pool_layers.{layer}"
        t[f"{p}.mlps_in.0.0.weight"] = (32, c_src, 1)
        t.update(_bn(f"{p}.mlps_in.0.1", 32))
        t[f"{p}.mlps_pos.0.0.weight"] = (32, 3, 1, 1)
        t.update(_bn(f"{p}.mlps_pos.0.1", 32))
        t[f"{p}.mlps_out.0.0.weight"] = (32, 32, 1)
        t.update(_bn(f"{p}.mlps_out.0.1", 32))
    t[f"{rh}.shared_fc_layer.0.weight"] = (256, 6 * 6 * 6 * 96)
    t.update(_bn(f"{rh}.shared_fc_layer.1", 256))
    t[f"{rh}.shared_fc_layer.4.weight"] = (256, 256)
    t.update(_bn(f"{rh}.shared_fc_layer.5", 256))
    for stack in ("cls_fc_layers", "reg_fc_layers"):
        t[f"{rh}.{stack}.0.weight"] = (256, 256)
        t.update(_bn(f"{rh}.{stack}.1", 256))
        t[f"{rh}.{stack}.4.weight"] = (256, 256)
        t.update(_bn(f"{rh}.{stack}.5", 256))
    t.update({f"{rh}.cls_pred_layer.weight": (1, 256), f"{rh}.cls_pred_layer.bias": (1,),
              f"{rh}.reg_pred_layer.weight": (7, 256), f"{rh}.reg_pred_layer.bias": (7,)})
    return t


def test_paper_model_loads_openpcdet_state_dict_strictly():
    expected = _openpcdet_voxel_rcnn_car()
    model = build_detector(copy.deepcopy(CONFIGS["paper"]), 1, ["Car"], KITTI_RANGE, KITTI_VOXEL)
    ours = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    assert ours == expected
    g = torch.Generator().manual_seed(0)
    foreign = {k: (torch.randint(0, 100, shape, generator=g) if k.endswith(("num_batches_tracked", "global_step"))
                   else torch.randn(shape, generator=g)) for k, shape in expected.items()}
    model.load_state_dict(foreign, strict=True)
    key = "backbone_3d.conv2.0.0.weight"
    assert torch.equal(model.state_dict()[key], foreign[key])
    # A checkpoint trained with spconv 1.x stores sparse weights as (k, k, k, in, out).
    old_layout = {k: v.permute(1, 2, 3, 4, 0).contiguous() if v.ndim == 5 else v for k, v in foreign.items()}
    assert old_layout[key].shape == (3, 3, 3, 16, 32)
    model.load_openpcdet_state(old_layout)
    assert torch.equal(model.state_dict()[key], foreign[key])
    assert torch.equal(model.state_dict()["backbone_3d.conv_out.0.weight"], foreign["backbone_3d.conv_out.0.weight"])


def _tiny_cfg() -> dict:
    """The small config with a smaller RoI stage so a CPU forward takes about a second."""
    cfg = copy.deepcopy(CONFIGS["small"])
    roi = cfg["ROI_HEAD"]
    roi["ROI_GRID_POOL"]["GRID_SIZE"] = 3
    for layer in roi["ROI_GRID_POOL"]["POOL_LAYERS"].values():
        layer["QUERY_RANGES"] = [[2, 2, 2]]
    roi["NMS_CONFIG"]["TRAIN"]["NMS_POST_MAXSIZE"] = 32
    roi["NMS_CONFIG"]["TEST"]["NMS_POST_MAXSIZE"] = 16
    roi["TARGET_CONFIG"]["ROI_PER_IMAGE"] = 16
    return cfg


def _box_points(box: torch.Tensor, n: int, g: torch.Generator) -> torch.Tensor:
    local = (torch.rand(n, 3, generator=g) - 0.5) * box[3:6]
    c, s = math.cos(float(box[6])), math.sin(float(box[6]))
    x = local[:, 0] * c - local[:, 1] * s + box[0]
    y = local[:, 0] * s + local[:, 1] * c + box[1]
    return torch.stack([x, y, local[:, 2] + box[2]], dim=1)


def _tiny_batch(seed: int = 0, max_points: int = 5) -> dict:
    """Two samples, each ground points plus two cars' worth of points, voxelised."""
    g = torch.Generator().manual_seed(seed)
    gt = torch.tensor([[2.0, -1.0, -1.0, 3.9, 1.6, 1.56, 0.3, 1.0],
                       [4.5, 1.5, -1.0, 3.9, 1.6, 1.56, 1.4, 1.0]])
    rows = []
    for b in range(2):
        ground = torch.rand(200, 3, generator=g) * torch.tensor([6.4, 6.4, 0.2]) + torch.tensor([0.0, -3.2, -1.8])
        xyz = torch.cat([ground, *[_box_points(box, 150, g) for box in gt]])
        rows.append(torch.cat([torch.full((len(xyz), 1), float(b)), xyz, torch.rand(len(xyz), 1, generator=g)], 1))
    points = torch.cat(rows)
    cell = ((points[:, 1:4] - torch.tensor(TINY_RANGE[:3])) / torch.tensor(TINY_VOXEL)).floor().long()
    inside = ((cell >= 0) & (cell < torch.tensor([32, 32, 40]))).all(dim=1)
    points, cell = points[inside], cell[inside]
    coords = torch.cat([points[:, :1].long(), cell[:, [2, 1, 0]]], dim=1)
    uniq, inverse = torch.unique(coords, dim=0, return_inverse=True)
    voxels = torch.zeros(len(uniq), max_points, 4)
    counts = torch.zeros(len(uniq), dtype=torch.long)
    for i, v in enumerate(inverse.tolist()):
        if counts[v] < max_points:
            voxels[v, counts[v]] = points[i, 1:]
            counts[v] += 1
    return {"batch_size": 2, "points": points, "voxels": voxels, "voxel_num_points": counts,
            "voxel_coords": uniq.int(), "gt_boxes": torch.stack([gt, torch.cat([gt[:1], torch.zeros(1, 8)])])}


def _tiny_model(seed: int = 0):
    torch.manual_seed(seed)
    return build_detector(_tiny_cfg(), 1, ["Car"], TINY_RANGE, TINY_VOXEL, seed=seed)


def test_training_forward_backward_gives_finite_loss_and_gradients():
    model = _tiny_model()
    model.train()
    ret, tb, _ = model(_tiny_batch())
    loss = ret["loss"]
    assert loss.ndim == 0 and torch.isfinite(loss)
    for key in ("rpn_loss_cls", "rpn_loss_loc", "rpn_loss_dir", "rcnn_loss_cls", "rcnn_loss_reg"):
        assert math.isfinite(tb[key])
    loss.backward()
    grads = [p.grad for p in model.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(g).all() for g in grads)
    assert model.backbone_3d.conv_input[0].weight.grad.abs().sum() > 0
    assert model.dense_head.conv_box.weight.grad.abs().sum() > 0
    assert model.roi_head.cls_pred_layer.weight.grad.abs().sum() > 0


def test_rois_near_the_boxes_train_the_refinement():
    """RoIs given next to the gt boxes (the proposal layer then keeps them) are
    foreground: the box regression and corner losses and their gradients appear."""
    model = _tiny_model()
    model.train()
    batch = _tiny_batch()
    g = torch.Generator().manual_seed(3)
    rois = batch["gt_boxes"][:, :, :7].clone()
    rois[..., :3] += 0.1 * torch.randn(rois[..., :3].shape, generator=g)
    rois[1, 1] = torch.tensor([5.0, -2.5, -1.0, 1.0, 1.0, 1.0, 0.0])  # a background RoI
    batch.update(rois=rois, roi_scores=torch.ones(2, 2), roi_labels=torch.ones(2, 2, dtype=torch.long))
    _, tb, _ = model(batch)
    ret = model.roi_head.forward_ret_dict
    assert ret["reg_valid_mask"].sum() > 0
    assert tb["rcnn_loss_reg"] > 0 and tb["rcnn_loss_corner"] > 0
    model.roi_head.get_loss()[0].backward()
    assert model.roi_head.reg_pred_layer.weight.grad.abs().sum() > 0


def test_eval_returns_contract_predictions_and_recall():
    model = _tiny_model()
    model.eval()
    batch = _tiny_batch()
    with torch.no_grad():
        pred_dicts, recall = model(batch)
    assert len(pred_dicts) == 2
    for pred in pred_dicts:
        assert set(pred) == {"pred_boxes", "pred_scores", "pred_labels"}
        k = len(pred["pred_scores"])
        assert pred["pred_boxes"].shape == (k, 7) and pred["pred_labels"].shape == (k,)
        assert k == 0 or (pred["pred_labels"] >= 1).all()
        assert (pred["pred_scores"] >= 0.3).all()  # POST_PROCESSING.SCORE_THRESH
        assert (pred["pred_boxes"][:, 3:6] > 0).all()  # nothing refined from RoI padding
    assert recall["gt"] == 3  # the zero padding row of sample 1 is not a box
    assert set(recall) == {"gt"} | {f"{s}_{t}" for s in ("roi", "rcnn") for t in (0.3, 0.5, 0.7)}


def test_optimisation_steps_reduce_the_loss():
    model = _tiny_model()
    model.train()
    optim_cfg = {"OPTIMIZER": "adam_onecycle", "LR": 0.01, "WEIGHT_DECAY": 0.01, "MOMS": [0.95, 0.85],
                 "PCT_START": 0.4, "DIV_FACTOR": 10, "GRAD_NORM_CLIP": 10}
    steps = 8
    optimizer, schedule = build_optimizer(model, optim_cfg, total_steps=steps)
    batch = _tiny_batch()
    losses, rpn_losses = [], []
    for step in range(steps):
        schedule.step(step)
        optimizer.zero_grad()
        ret, tb, _ = model(dict(batch))
        rpn_losses.append(tb["rpn_loss"])
        ret["loss"].backward()
        clip_gradients(model, optim_cfg)
        optimizer.step()
        losses.append(ret["loss"].item())
    # The RoI losses start late (no foreground RoI before the RPN learns), so the
    # total is noisier than the RPN's part.
    assert losses[-1] < 0.7 * losses[0], losses
    assert rpn_losses[-1] < 0.5 * rpn_losses[0], rpn_losses


def test_one_cycle_schedule_matches_fastai_shape():
    model = torch.nn.Linear(2, 2)
    cfg = {"OPTIMIZER": "adam_onecycle", "LR": 0.01, "MOMS": [0.95, 0.85], "PCT_START": 0.4, "DIV_FACTOR": 10}
    optimizer, schedule = build_optimizer(model, cfg, total_steps=100)
    group = optimizer.param_groups[0]
    schedule.step(0)
    assert group["lr"] == pytest.approx(0.001) and group["betas"][0] == pytest.approx(0.95)
    schedule.step(40)
    assert group["lr"] == pytest.approx(0.01) and group["betas"][0] == pytest.approx(0.85)
    schedule.step(20)
    assert group["lr"] == pytest.approx(0.0055)  # half way up the first half-cosine
    schedule.step(99)
    assert 1e-7 < group["lr"] < 1e-5 and group["betas"][0] == pytest.approx(0.95, abs=1e-3)
    lower_case = adam_onecycle(model, {"lr": 0.01, "moms": [0.95, 0.85], "pct_start": 0.4, "div_factor": 10}, 100)[1]
    lower_case(20)  # callable with the step, as the training hook uses it
    assert lower_case.optimizer.param_groups[0]["lr"] == pytest.approx(0.0055)
    with pytest.raises(InputError, match="OPTIMIZER 'sgd'"):
        build_optimizer(model, {"OPTIMIZER": "sgd", "LR": 0.1}, 10)


def test_residual_coder_round_trip():
    g = torch.Generator().manual_seed(1)
    anchors = torch.cat([torch.randn(50, 3, generator=g), torch.rand(50, 3, generator=g) + 0.5,
                         torch.randn(50, 1, generator=g)], 1)
    boxes = torch.cat([torch.randn(50, 3, generator=g), torch.rand(50, 3, generator=g) + 0.5,
                       torch.randn(50, 1, generator=g)], 1)
    coder = ResidualCoder()
    assert torch.allclose(coder.decode_torch(coder.encode_torch(boxes, anchors), anchors), boxes, atol=1e-5)


def test_anchor_layout_matches_openpcdet():
    cfg = CONFIGS["paper"]["DENSE_HEAD"]["ANCHOR_GENERATOR_CONFIG"]
    anchors, per_location = generate_anchors(KITTI_RANGE, cfg, [1408, 1600, 40])
    assert per_location == [2]
    a = anchors[0]
    assert a.shape == (1, 200, 176, 1, 2, 7)  # z, y, x, sizes, rotations
    # Edge-aligned: the first and last anchors sit on the range's borders; z is the box centre.
    assert torch.allclose(a[0, 0, 0, 0, 1], torch.tensor([0.0, -40.0, -1.78 + 0.78, 3.9, 1.6, 1.56, 1.57]))
    assert torch.allclose(a[0, -1, -1, 0, 0, :2], torch.tensor([70.4, 40.0]))


def test_bad_model_config_raises_input_error():
    cfg = copy.deepcopy(CONFIGS["small"])
    cfg["MAP_TO_BEV"]["NUM_BEV_FEATURES"] = 48
    with pytest.raises(InputError, match="NUM_BEV_FEATURES is 48 but the 3D backbone on this grid gives 64"):
        build_detector(cfg, 1, ["Car"], TINY_RANGE, TINY_VOXEL)
    # 25 z cells leave one slice after conv_out: 32 channels, not 64.
    with pytest.raises(InputError, match="gives 32"):
        build_detector(CONFIGS["small"], 1, ["Car"], TINY_RANGE, [0.2, 0.2, 0.16])
    # 47 x 47 BEV cells at stride 8: the stride-2 level upsamples to 48, OpenPCDet would fail in torch.cat.
    with pytest.raises(InputError, match=r"a 47 x 47 BEV map gives levels of sizes \[\(47, 47\), \(48, 48\)\]"):
        build_detector(CONFIGS["small"], 1, ["Car"], [0.0, -37.6, -2.0, 75.2, 37.6, 2.0], [0.2, 0.2, 0.1])
    # An odd grid: the backbone pads to 4 cells, the anchors (grid // 8) see 3.
    with pytest.raises(InputError, match=r"anchors lie on a \(3, 3\) map"):
        build_detector(CONFIGS["small"], 1, ["Car"], [0.0, -3.0, -2.0, 6.0, 3.0, 2.0], [0.2, 0.2, 0.1])
    broken = copy.deepcopy(CONFIGS["small"])
    del broken["ROI_HEAD"]["SHARED_FC"]
    with pytest.raises(InputError, match="det.yaml: MODEL config lacks key 'SHARED_FC'"):
        build_detector(broken, 1, ["Car"], TINY_RANGE, TINY_VOXEL, source="det.yaml")
    with pytest.raises(InputError, match="VoxelRCNNX"):
        build_detector({**CONFIGS["small"], "NAME": "VoxelRCNNX"}, 1, ["Car"], TINY_RANGE, TINY_VOXEL)


def test_target_assigner_marks_the_matching_anchor_and_encodes_its_box():
    from omnilidar.downstream.det.models.target_assigner import AxisAlignedTargetAssigner

    head_cfg = copy.deepcopy(CONFIGS["small"]["DENSE_HEAD"])
    anchors, _ = generate_anchors(TINY_RANGE, head_cfg["ANCHOR_GENERATOR_CONFIG"], [32, 32, 40])
    flat = anchors[0].reshape(-1, 7)
    target = flat[11].clone()
    target[0] += 0.3  # a little off the anchor: still its best match (IoU > 0.6)
    gt = torch.zeros(1, 3, 8)
    gt[0, 0, :7], gt[0, 0, 7] = target, 1
    assigner = AxisAlignedTargetAssigner(head_cfg, ["Car"], ResidualCoder(), torch.Generator().manual_seed(0))
    out = assigner.assign_targets(anchors, gt)
    labels = out["box_cls_labels"][0]
    assert labels[11] == 1 and out["reg_weights"][0, 11] == 1
    decoded = ResidualCoder().decode_torch(out["box_reg_targets"][0, 11], flat[11])
    assert torch.allclose(decoded, target, atol=1e-5)
    # The anchor rotated by 90 degrees at the same place overlaps the box less in
    # rounded BEV IoU (1.6 x 3.9 crossed with 3.9 x 1.6): background, no regression.
    other = 10
    assert flat[other, :2].allclose(flat[11, :2]) and float(flat[other, 6]) == 0.0
    assert labels[other] == 0 and out["reg_weights"][0, other] == 0
    assert (labels >= 0).all()  # POS_FRACTION -1: no anchor is left unassigned here


def test_proposal_target_layer_samples_foreground_share_and_soft_labels():
    from omnilidar.downstream.det.models.proposal_target_layer import ProposalTargetLayer

    cfg = dict(CONFIGS["paper"]["ROI_HEAD"]["TARGET_CONFIG"], ROI_PER_IMAGE=20)
    gt_box = torch.tensor([10.0, 0.0, -1.0, 4.0, 2.0, 1.5, 0.0])
    rois = gt_box.repeat(40, 1)
    rois[:10, 0] += torch.linspace(0.0, 0.3, 10)  # foreground (IoU > 0.9)
    rois[10:20, 0] += 2.0  # IoU 1/3: hard background, soft label
    rois[20:, 0] += 20.0  # IoU 0: easy background
    batch = {"batch_size": 1, "rois": rois[None], "roi_scores": torch.rand(1, 40),
             "roi_labels": torch.ones(1, 40, dtype=torch.long),
             "gt_boxes": torch.cat([gt_box, torch.tensor([1.0])])[None, None]}
    out = ProposalTargetLayer(cfg, torch.Generator().manual_seed(0)).forward(batch)
    ious = out["gt_iou_of_rois"][0]
    assert out["rois"].shape == (1, 20, 7)
    assert (ious[:10] > 0.55).all() and (ious[10:] < 0.55).all()  # FG_RATIO 0.5 of 20
    assert len(set(out["rois"][0, :10, 0].tolist())) == 10  # foreground drawn without replacement
    hard = (ious[10:] >= 0.1).sum()
    assert hard == int(10 * 0.8)  # HARD_BG_RATIO
    labels = out["rcnn_cls_labels"][0]
    assert (labels[:10] == 1).all()
    soft = (ious[10:] - 0.25) / 0.5
    expected = torch.where(ious[10:] < 0.25, torch.zeros_like(soft), soft)
    assert torch.allclose(labels[10:], expected)
    assert torch.equal(out["reg_valid_mask"][0], (ious > 0.55).long())


def test_roi_targets_are_in_the_roi_frame_with_flipped_heading():
    from omnilidar.downstream.det.models.roi_head_template import RoIHeadTemplate

    head = RoIHeadTemplate(1, CONFIGS["paper"]["ROI_HEAD"])
    roi = torch.tensor([5.0, 2.0, -1.0, 4.0, 2.0, 1.5, 0.5])
    gt = roi.clone()
    gt[6] += math.pi  # same box facing the other way
    gt[0] += 1.0
    batch = {"batch_size": 1, "rois": roi.repeat(4, 1)[None], "roi_scores": torch.ones(1, 4),
             "roi_labels": torch.ones(1, 4, dtype=torch.long),
             "gt_boxes": torch.cat([gt, torch.tensor([1.0])])[None, None]}
    head.proposal_target_layer.cfg = dict(head.proposal_target_layer.cfg, ROI_PER_IMAGE=4)
    out = head.assign_targets(batch)
    local = out["gt_of_rois"][0, 0]
    # A 1 m shift along the lidar x axis seen from a RoI turned by 0.5 rad.
    assert torch.allclose(local[:3], torch.tensor([math.cos(0.5), -math.sin(0.5), 0.0]), atol=1e-5)
    assert abs(float(local[6])) < 1e-5  # heading flipped by pi into (-pi/2, pi/2)
    assert torch.allclose(out["gt_of_rois_src"][0, 0, :7], gt)


def test_post_processing_scores_nms_labels_and_skips_padding_rois():
    from omnilidar.downstream.det.models.post_processing import post_processing

    boxes = torch.tensor([[[5.0, 0.0, -1.0, 4.0, 2.0, 1.5, 0.0],
                           [5.1, 0.0, -1.0, 4.0, 2.0, 1.5, 0.0],  # suppressed by the first
                           [15.0, 3.0, -1.0, 4.0, 2.0, 1.5, 1.0],
                           [25.0, 3.0, -1.0, 4.0, 2.0, 1.5, 1.0],  # under SCORE_THRESH
                           [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]]])  # refined from a padding RoI
    logits = torch.tensor([[[3.0], [2.0], [1.0], [-3.0], [4.0]]])
    gt = torch.tensor([[[5.0, 0.2, -1.0, 4.0, 2.0, 1.5, 0.0, 1.0], [40.0, 0.0, -1.0, 4.0, 2.0, 1.5, 0.0, 2.0]]])
    batch = {"batch_size": 1, "batch_box_preds": boxes, "batch_cls_preds": logits, "cls_preds_normalized": False,
             "rois": boxes.clone(), "roi_labels": torch.tensor([[2, 2, 1, 1, 0]]), "has_class_labels": True,
             "gt_boxes": gt}
    preds, recall = post_processing(batch, CONFIGS["paper"]["POST_PROCESSING"], num_class=2)
    assert torch.equal(preds[0]["pred_boxes"], boxes[0, [0, 2]])
    assert torch.allclose(preds[0]["pred_scores"], torch.sigmoid(torch.tensor([3.0, 1.0])))
    assert preds[0]["pred_labels"].tolist() == [2, 1]  # the RoIs' labels (has_class_labels)
    assert recall == {"gt": 2, "roi_0.3": 1, "rcnn_0.3": 1, "roi_0.5": 1, "rcnn_0.5": 1,
                      "roi_0.7": 1, "rcnn_0.7": 1}
