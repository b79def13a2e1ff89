"""PV-RCNN's own modules: set abstraction, keypoint head, RoI-grid head, detector wiring."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F
import yaml
from det_pvrcnn_keys import pv_rcnn_kitti_keys

from omnilidar.dicts import deep_merge
from omnilidar.downstream.det.models.detector import build_detector
from omnilidar.downstream.det.models.point_head_simple import PointHeadSimple
from omnilidar.downstream.det.models.pointnet2_stack import StackSAModuleMSG
from omnilidar.downstream.det.models.voxel_rcnn_head import VoxelRCNNHead
from omnilidar.downstream.det.models.voxel_set_abstraction import VoxelSetAbstraction, bilinear_interpolate
from omnilidar.errors import InputError
from omnilidar.sparse.tensor import SparseTensor

POINT_CLOUD_RANGE = [0.0, -4.0, -2.0, 8.0, 4.0, 2.0]
VOXEL_SIZE = [0.1, 0.1, 0.2]


def random_points(batch_size: int, n: int, seed: int) -> torch.Tensor:
    """(B * n, 5) [batch, x, y, z, intensity] inside POINT_CLOUD_RANGE."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor(POINT_CLOUD_RANGE[:3]), torch.tensor(POINT_CLOUD_RANGE[3:])
    xyz = lo + torch.rand(batch_size * n, 3, generator=g) * (hi - lo) * 0.999
    batch = torch.arange(batch_size).repeat_interleave(n)[:, None].float()
    return torch.cat([batch, xyz, torch.rand(batch_size * n, 1, generator=g)], dim=1)


def sparse_map(points: torch.Tensor, channels: int, stride: int, batch_size: int, seed: int) -> SparseTensor:
    """Occupied voxels of ``points`` at ``stride`` with random features; rows batch, z, y, x
    on a (Z, Y, X) grid, as the detection backbone lays them out."""
    g = torch.Generator().manual_seed(seed)
    origin, size = torch.tensor(POINT_CLOUD_RANGE[:3]), torch.tensor(VOXEL_SIZE) * stride
    zyx = ((points[:, 1:4] - origin) / size).floor().int()[:, [2, 1, 0]]
    coords = torch.unique(torch.cat([points[:, :1].int(), zyx], dim=1), dim=0)
    grid = [math.ceil(20 / stride), math.ceil(80 / stride), math.ceil(80 / stride)]
    return SparseTensor(torch.randn(coords.shape[0], channels, generator=g), coords, grid, batch_size)


def test_stack_sa_module_pools_the_first_neighbours_in_the_ball():
    torch.manual_seed(0)
    module = StackSAModuleMSG(radii=[0.5], nsamples=[4], mlps=[[2, 5]]).eval()
    xyz = torch.tensor([[0.0, 0, 0], [0.1, 0, 0], [3, 3, 3], [0.2, 0.1, 0], [0.3, 0, 0], [0.0, 0.4, 0],
                        [0.0, 0, 0]])
    feats = torch.randn(7, 2)
    xyz_cnt = torch.tensor([6, 1], dtype=torch.int32)
    centres = torch.tensor([[0.05, 0.0, 0.0], [10.0, 0, 0], [0.0, 0.0, 0.1]])
    centre_cnt = torch.tensor([2, 1], dtype=torch.int32)
    _, out = module(xyz, xyz_cnt, centres, centre_cnt, feats)
    assert out.shape == (3, 5)

    def reference(neigh: list[int], centre: torch.Tensor, offset: int = 0) -> torch.Tensor:
        rows = [torch.cat([xyz[offset + i] - centre, feats[offset + i]]) for i in neigh]
        x = torch.stack(rows, dim=1)[None, :, None, :] if rows else torch.zeros(1, 5, 1, 4)
        return module.mlps[0](x).amax(dim=3).view(-1)

    # sample 0, centre 0: points 0, 1, 3, 4 lie within 0.5 (point 5 at 0.4 is the fifth: dropped)
    assert torch.allclose(out[0], reference([0, 1, 3, 4], centres[0]), atol=1e-5)
    # sample 0, centre 1: nothing within the radius -> the MLP of all-zero columns
    assert torch.allclose(out[1], reference([], centres[1]), atol=1e-5)
    # sample 1 only sees its own point (index 6), never sample 0's point 0 at the same place
    assert torch.allclose(out[2], reference([0, 0, 0, 0], centres[2], offset=6), atol=1e-5)


def test_bilinear_interpolation_matches_grid_sample_inside_the_map():
    g = torch.Generator().manual_seed(1)
    image = torch.randn(5, 7, 3, generator=g)  # (H, W, C)
    x = torch.rand(50, generator=g) * 6
    y = torch.rand(50, generator=g) * 4
    ours = bilinear_interpolate(image, x, y)
    grid = torch.stack([x / 6 * 2 - 1, y / 4 * 2 - 1], dim=1).view(1, 1, -1, 2)
    ref = F.grid_sample(image.permute(2, 0, 1)[None], grid, align_corners=True).view(3, -1).t()
    assert torch.allclose(ours, ref, atol=1e-5)
    # the last half cell replicates the border instead of fading to zero (OpenPCDet's quirk)
    edge = bilinear_interpolate(image, torch.tensor([6.5]), torch.tensor([4.5]))
    assert torch.allclose(edge[0], image[4, 6], atol=1e-6)


def vsa_config(num_keypoints: int = 32) -> dict:
    return {
        "NAME": "VoxelSetAbstraction", "POINT_SOURCE": "raw_points", "NUM_KEYPOINTS": num_keypoints,
        "NUM_OUTPUT_FEATURES": 24, "SAMPLE_METHOD": "FPS",
        "FEATURES_SOURCE": ["bev", "x_conv1", "x_conv2", "raw_points"],
        "SA_LAYER": {
            "raw_points": {"MLPS": [[8, 8], [8, 8]], "POOL_RADIUS": [0.4, 0.8], "NSAMPLE": [8, 8]},
            "x_conv1": {"DOWNSAMPLE_FACTOR": 1, "MLPS": [[4, 4]], "POOL_RADIUS": [0.4], "NSAMPLE": [8]},
            "x_conv2": {"DOWNSAMPLE_FACTOR": 2, "INPUT_CHANNELS": 6, "MLPS": [[8, 8]], "POOL_RADIUS": [0.8],
                        "NSAMPLE": [8]},
        },
    }


def vsa_batch(batch_size: int = 2, n: int = 200) -> dict:
    points = random_points(batch_size, n, seed=2)
    return {
        "batch_size": batch_size,
        "points": points,
        "multi_scale_3d_features": {
            "x_conv1": sparse_map(points, 4, 1, batch_size, seed=3),
            "x_conv2": sparse_map(points, 6, 2, batch_size, seed=4),
        },
        "spatial_features": torch.randn(batch_size, 5, 10, 10, generator=torch.Generator().manual_seed(5)),
        "spatial_features_stride": 8,
    }


def test_voxel_set_abstraction_shapes_keypoints_and_gradients():
    torch.manual_seed(0)
    vsa = VoxelSetAbstraction(vsa_config(), VOXEL_SIZE, POINT_CLOUD_RANGE, num_bev_features=5,
                              num_rawpoint_features=4)
    assert vsa.num_point_features_before_fusion == 5 + 4 + 8 + 16
    batch = vsa_batch()
    batch["spatial_features"].requires_grad_(True)
    out = vsa(batch)
    coords = out["point_coords"]
    assert coords.shape == (64, 4) and out["point_features"].shape == (64, 24)
    assert out["point_features_before_fusion"].shape == (64, 33)
    # keypoints are distinct raw points of their own sample, the first one FPS's start (index 0)
    for b in range(2):
        kp = coords[coords[:, 0] == b, 1:4]
        own = batch["points"][batch["points"][:, 0] == b, 1:4]
        assert kp.shape[0] == 32 and torch.unique(kp, dim=0).shape[0] == 32
        assert torch.equal(kp[0], own[0])
        assert bool((kp[:, None] == own[None]).all(dim=2).any(dim=1).all())
    out["point_features"].sum().backward()
    assert batch["spatial_features"].grad.abs().sum() > 0
    assert all(p.grad is not None for p in vsa.SA_layers.parameters() if p.requires_grad)


def test_voxel_set_abstraction_repeats_keypoints_of_a_sparse_sample():
    vsa = VoxelSetAbstraction(vsa_config(num_keypoints=12), VOXEL_SIZE, POINT_CLOUD_RANGE,
                              num_bev_features=5, num_rawpoint_features=4).eval()
    batch = vsa_batch(batch_size=1, n=5)
    coords = vsa(batch)["point_coords"]
    assert coords.shape == (12, 4)
    assert torch.equal(coords[:5], coords[5:10]) and torch.equal(coords[:2], coords[10:12])
    assert torch.unique(coords[:5, 1:4], dim=0).shape[0] == 5


def test_voxel_set_abstraction_rejects_a_mismatched_backbone_width():
    vsa = VoxelSetAbstraction(vsa_config(), VOXEL_SIZE, POINT_CLOUD_RANGE, num_bev_features=5,
                              num_rawpoint_features=4)
    batch = vsa_batch()
    batch["multi_scale_3d_features"]["x_conv2"] = sparse_map(batch["points"], 7, 2, 2, seed=4)
    with pytest.raises(ValueError, match="x_conv2 expects 6 input channels"):
        vsa(batch)


def point_head(num_class: int) -> PointHeadSimple:
    cfg = {"NAME": "PointHeadSimple", "CLS_FC": [8], "CLASS_AGNOSTIC": num_class == 1,
           "USE_POINT_FEATURES_BEFORE_FUSION": True, "TARGET_CONFIG": {"GT_EXTRA_WIDTH": [0.2, 0.2, 0.2]},
           "LOSS_CONFIG": {"LOSS_REG": "smooth-l1", "LOSS_WEIGHTS": {"point_cls_weight": 1.0}}}
    return PointHeadSimple(num_class=num_class, input_channels=6, model_cfg=cfg)


def test_point_head_targets_foreground_ignore_margin_and_background():
    # sample 0: a 2 x 1 x 1 box rotated by 90 deg (so 1 m along x, 2 m along y) at the origin, class 2;
    # sample 1: one class-1 box at x = 5; padding row (class 0) must be skipped
    gt = torch.tensor([
        [[0.0, 0.0, 0.0, 2.0, 1.0, 1.0, math.pi / 2, 2], [0, 0, 0, 0, 0, 0, 0, 0]],
        [[5.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0, 1], [0, 0, 0, 0, 0, 0, 0, 0]],
    ])
    coords = torch.tensor([
        [0, 0.0, 0.9, 0.0],    # inside (along the rotated long side)
        [0, 0.9, 0.0, 0.0],    # outside: x half-extent is 0.5 after rotation
        [0, 0.55, 0.0, 0.0],   # in the 0.1 m enlarged margin -> ignored
        [0, 0.0, 0.0, 0.58],   # in the z margin -> ignored
        [1, 5.0, 0.0, 0.0],    # inside the sample-1 box
        [1, 0.0, 0.9, 0.0],    # would be inside sample 0's box, but belongs to sample 1
    ])
    assert point_head(1).assign_targets(coords, gt).tolist() == [1, 0, -1, -1, 1, 0]
    assert point_head(3).assign_targets(coords, gt).tolist() == [2, 0, -1, -1, 1, 0]


def test_point_head_focal_loss_and_scores():
    torch.manual_seed(0)
    head = point_head(1)
    feats = torch.randn(6, 6, requires_grad=True)
    batch = {"point_features_before_fusion": feats, "point_features": torch.randn(6, 3),
             "point_coords": torch.tensor([[0, 0.0, 0, 0]] * 3 + [[0, 9.0, 0, 0]] * 3),
             "gt_boxes": torch.tensor([[[0.0, 0, 0, 1, 1, 1, 0, 1]]])}
    head.train()
    batch = head(batch)
    loss, tb = head.get_loss()
    logits = head.forward_ret_dict["point_cls_preds"].view(-1)
    assert torch.allclose(batch["point_cls_scores"], torch.sigmoid(logits))
    p = torch.sigmoid(logits)
    target = torch.tensor([1.0, 1, 1, 0, 0, 0])
    alpha = torch.where(target > 0, 0.25, 0.75)
    p_wrong = torch.where(target > 0, 1 - p, p)
    expected = (alpha * p_wrong ** 2 * F.binary_cross_entropy_with_logits(logits, target, reduction="none")).sum() / 3
    assert torch.allclose(loss, expected, atol=1e-6)
    assert tb["point_pos_num"] == 3.0
    loss.backward()
    assert feats.grad.abs().sum() > 0


def test_roi_grid_points_cell_centres_rotated_with_the_box():
    rois = torch.tensor([[1.0, 2.0, 3.0, 4.0, 2.0, 2.0, 0.0], [0.0, 0.0, 0.0, 4.0, 2.0, 2.0, math.pi / 2]])
    grid = VoxelRCNNHead.grid_points_of_rois(rois, 2)  # PV-RCNN's flattening order relies on it
    assert grid.shape == (2, 8, 3)
    # x-major order: (ix, iy, iz) = (0,0,0), (0,0,1), (0,1,0), ... ; cell centres at +-size/4
    assert torch.allclose(grid[0, 0], torch.tensor([0.0, 1.5, 2.5]))
    assert torch.allclose(grid[0, 1], torch.tensor([0.0, 1.5, 3.5]))
    assert torch.allclose(grid[0, 2], torch.tensor([0.0, 2.5, 2.5]))
    assert torch.allclose(grid[0, 4], torch.tensor([2.0, 1.5, 2.5]))
    # heading 90 deg: local +x (length) points along world +y
    assert torch.allclose(grid[1, 4], torch.tensor([0.5, 1.0, -0.5]), atol=1e-6)


def test_voxel_set_abstraction_accepts_voxels_not_grouped_by_sample():
    torch.manual_seed(0)
    vsa = VoxelSetAbstraction(vsa_config(), VOXEL_SIZE, POINT_CLOUD_RANGE, num_bev_features=5,
                              num_rawpoint_features=4).eval()
    batch = vsa_batch()
    expected = vsa(dict(batch))["point_features"]
    # interleave the samples' voxels, keeping each sample's own order (spconv need not group them)
    conv1 = batch["multi_scale_3d_features"]["x_conv1"]
    b = conv1.coords[:, 0].long()
    rank = torch.cat([torch.arange(int((b == k).sum())) for k in range(2)])
    order = torch.argsort(rank * 2 + b, stable=True)
    assert not torch.equal(b[order], b.sort().values)
    batch["multi_scale_3d_features"]["x_conv1"] = SparseTensor(conv1.feats[order], conv1.coords[order],
                                                                conv1.spatial_shape, 2)
    assert torch.allclose(vsa(dict(batch))["point_features"], expected, atol=1e-6)


def test_voxel_set_abstraction_pools_voxels_at_their_metric_centres():
    torch.manual_seed(0)
    cfg = vsa_config(num_keypoints=3)
    cfg["FEATURES_SOURCE"] = ["x_conv1"]
    vsa = VoxelSetAbstraction(cfg, VOXEL_SIZE, POINT_CLOUD_RANGE, num_rawpoint_features=4).eval()
    points = torch.tensor([[0, 1.01, -3.55, 0.3, 0.5], [0, 6.22, 2.71, -1.5, 0.1], [0, 3.33, 0.04, 1.7, 0.9]])
    conv1 = sparse_map(points, 4, 1, 1, seed=6)
    out = vsa({"batch_size": 1, "points": points, "multi_scale_3d_features": {"x_conv1": conv1}})
    # the voxel centres by hand: cell corner + half a cell, x/y 0.1 m and z 0.2 m cells
    origin, size = torch.tensor(POINT_CLOUD_RANGE[:3]), torch.tensor(VOXEL_SIZE)
    centres = (((points[:, 1:4] - origin) / size).floor() + 0.5) * size + origin
    # match each point's voxel row by its (z, y, x) index
    zyx = ((points[:, 1:4] - origin) / size).floor().int()[:, [2, 1, 0]]
    rows = [int(((conv1.coords[:, 1:4] == zyx[i]).all(dim=1)).nonzero()[0, 0]) for i in range(3)]
    cnt = torch.tensor([3], dtype=torch.int32)
    _, expected = vsa.SA_layers[0](centres, cnt, out["point_coords"][:, 1:4], cnt, conv1.feats[rows])
    assert torch.allclose(out["point_features_before_fusion"], expected, atol=1e-6)
    # and the keypoints do find their voxel (not the empty-ball response)
    _, empty = vsa.SA_layers[0](centres + 50, cnt, out["point_coords"][:, 1:4], cnt, conv1.feats[rows])
    assert not torch.allclose(expected, empty, atol=1e-3)


# --- the whole detector (det-voxelrcnn's chain + the modules above) ---------------------------------

CONFIG = Path(__file__).resolve().parents[1] / "config" / "detectors" / "pv_rcnn.yaml"
TINY_RANGE = [0.0, -8.0, -2.0, 12.8, 8.0, 2.0]  # 128 x 160 x 40 cells: 2 z slices after the backbone
TINY_VOXEL = [0.1, 0.1, 0.1]
TINY_ANCHORS = [
    {"class_name": "Car", "anchor_sizes": [[3.9, 1.6, 1.56]], "anchor_rotations": [0, 1.57],
     "anchor_bottom_heights": [-1.78], "align_center": False, "feature_map_stride": 8,
     "matched_threshold": 0.6, "unmatched_threshold": 0.45},
    {"class_name": "Pedestrian", "anchor_sizes": [[0.8, 0.6, 1.73]], "anchor_rotations": [0, 1.57],
     "anchor_bottom_heights": [-0.6], "align_center": False, "feature_map_stride": 8,
     "matched_threshold": 0.5, "unmatched_threshold": 0.35},
]


def model_configs() -> dict:
    doc = yaml.safe_load(CONFIG.read_text())
    return {"paper": doc["MODEL"], "small": deep_merge(doc["MODEL"], doc["CPU_SMALL"])}


def tiny_model_config() -> dict:
    cfg = model_configs()["small"]
    cfg["DENSE_HEAD"]["ANCHOR_GENERATOR_CONFIG"] = TINY_ANCHORS
    cfg["PFE"]["NUM_KEYPOINTS"] = 128
    return cfg


def tiny_batch(seed: int = 0) -> dict:
    """Two frames: scattered ground points plus a car and a pedestrian full of points."""
    g = torch.Generator().manual_seed(seed)
    boxes = torch.tensor([[[5.0, -2.0, -0.9, 3.9, 1.6, 1.56, 0.3, 1], [8.0, 3.0, -0.6, 0.8, 0.6, 1.73, 0.0, 2]],
                          [[7.0, 2.0, -0.9, 3.9, 1.6, 1.56, -0.5, 1], [0, 0, 0, 0, 0, 0, 0, 0]]])
    frames = []
    for b in range(2):
        ground = torch.rand(200, 3, generator=g) * torch.tensor([12.7, 15.9, 0.2]) + torch.tensor([0.0, -7.95, -1.9])
        parts = [ground]
        for box in boxes[b][boxes[b, :, 7] > 0]:
            local = (torch.rand(80, 3, generator=g) - 0.5) * box[3:6] * 0.9
            c, s = math.cos(float(box[6])), math.sin(float(box[6]))
            world = torch.stack([local[:, 0] * c - local[:, 1] * s, local[:, 0] * s + local[:, 1] * c, local[:, 2]], 1)
            parts.append(world + box[0:3])
        xyz = torch.cat(parts)
        frames.append(torch.cat([torch.full((len(xyz), 1), float(b)), xyz, torch.rand(len(xyz), 1, generator=g)], 1))
    points = torch.cat(frames)
    # one point per voxel (the first), OpenPCDet's voxel layout
    origin, size = torch.tensor(TINY_RANGE[:3]), torch.tensor(TINY_VOXEL)
    zyx = ((points[:, 1:4] - origin) / size).floor().long()[:, [2, 1, 0]]
    coords, inverse = torch.unique(torch.cat([points[:, :1].long(), zyx], 1), dim=0, return_inverse=True)
    first = torch.full((len(coords),), len(points), dtype=torch.long).scatter_reduce(
        0, inverse, torch.arange(len(points)), reduce="amin")
    return {"batch_size": 2, "points": points, "voxels": points[first, 1:][:, None, :],
            "voxel_num_points": torch.ones(len(coords), dtype=torch.int32), "voxel_coords": coords.int(),
            "gt_boxes": boxes}


def test_openpcdet_pv_rcnn_state_dict_loads_strictly():
    torch.manual_seed(0)
    model = build_detector(model_configs()["paper"], 3, ["Car", "Pedestrian", "Cyclist"],
                           [0.0, -40.0, -3.0, 70.4, 40.0, 1.0], [0.05, 0.05, 0.1])
    expected = pv_rcnn_kitti_keys()
    g = torch.Generator().manual_seed(0)
    state = {k: (torch.randint(0, 9, shape, generator=g) if k.endswith("num_batches_tracked") or k == "global_step"
                 else torch.randn(shape, generator=g)) for k, shape in expected.items()}
    model.load_state_dict(state, strict=True)
    own = model.state_dict()
    assert {k: tuple(v.shape) for k, v in own.items()} == expected
    assert torch.equal(own["roi_head.shared_fc_layer.0.weight"], state["roi_head.shared_fc_layer.0.weight"])
    assert torch.equal(own["pfe.SA_rawpoints.mlps.1.3.weight"], state["pfe.SA_rawpoints.mlps.1.3.weight"])
    # the published checkpoint (spconv 1.x) stores sparse weights as (k, k, k, in, out)
    old_layout = {k: v.permute(1, 2, 3, 4, 0).contiguous() if v.ndim == 5 else v for k, v in state.items()}
    model.load_openpcdet_state(old_layout, strict=True)
    assert torch.equal(model.state_dict()["backbone_3d.conv2.0.0.weight"], state["backbone_3d.conv2.0.0.weight"])


def test_pv_rcnn_trains_and_predicts_on_a_tiny_batch():
    torch.manual_seed(0)
    model = build_detector(tiny_model_config(), 2, ["Car", "Pedestrian"], TINY_RANGE, TINY_VOXEL)
    model.train()
    ret, tb, _ = model(tiny_batch())
    loss = ret["loss"]
    assert loss.ndim == 0 and torch.isfinite(loss)
    assert {"point_loss_cls", "point_pos_num", "rcnn_loss_cls", "rcnn_loss_reg"} <= set(tb)
    assert tb["point_pos_num"] > 0  # keypoints landed inside the boxes
    loss.backward()
    for name in ("pfe.vsa_point_feature_fusion.0.weight", "point_head.cls_layers.0.weight",
                 "roi_head.roi_grid_pool_layer.mlps.0.0.weight", "roi_head.shared_fc_layer.0.weight",
                 "backbone_3d.conv1.0.0.weight"):
        grad = dict(model.named_parameters())[name].grad
        assert grad is not None and torch.isfinite(grad).all() and grad.abs().sum() > 0, name

    model.eval()
    with torch.no_grad():
        preds, recall = model(tiny_batch())  # gt_boxes kept: recall needs them, as in OpenPCDet
    assert len(preds) == 2
    for pred in preds:
        k = pred["pred_boxes"].shape[0]
        assert pred["pred_boxes"].shape == (k, 7) and pred["pred_scores"].shape == (k,)
        assert pred["pred_labels"].shape == (k,) and pred["pred_labels"].dtype == torch.long
        assert bool(((pred["pred_labels"] >= 1) & (pred["pred_labels"] <= 2)).all())
    assert {"gt", "roi_0.3", "rcnn_0.3", "roi_0.7", "rcnn_0.7"} <= set(recall)
    assert recall["gt"] == 3


def test_pv_rcnn_fits_one_batch():
    torch.manual_seed(0)
    model = build_detector(tiny_model_config(), 2, ["Car", "Pedestrian"], TINY_RANGE, TINY_VOXEL).train()
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses, point_losses = [], []
    for _ in range(8):
        optimizer.zero_grad()
        ret, tb, _ = model(tiny_batch())
        ret["loss"].backward()
        optimizer.step()
        losses.append(float(ret["loss"].detach()))
        point_losses.append(tb["point_loss_cls"])
    assert sum(losses[-3:]) < 0.8 * sum(losses[:3]), losses
    assert point_losses[-1] < 0.5 * point_losses[0], point_losses  # the keypoint head learns


def test_pvrcnn_head_flattens_the_pooled_grid_channel_major():
    """shared_fc_layer.0 sees column c * G^3 + g for channel c at grid cell g (OpenPCDet's
    layout, which its checkpoints' first shared FC weights assume)."""
    torch.manual_seed(0)
    cfg = tiny_model_config()
    model = build_detector(cfg, 2, ["Car", "Pedestrian"], TINY_RANGE, TINY_VOXEL).eval()
    head = model.roi_head
    g3, c = cfg["ROI_HEAD"]["ROI_GRID_POOL"]["GRID_SIZE"] ** 3, 32
    pooled = torch.zeros(1, g3, c)
    pooled[0, 5, 3] = 1.0  # grid cell 5, channel 3
    head.roi_grid_pool = lambda batch_dict: pooled
    first = head.shared_fc_layer[0]
    with torch.no_grad():
        first.weight.zero_()
        first.weight[0, 3 * g3 + 5, 0] = 2.0
    seen = {}
    first.register_forward_hook(lambda m, i, o: seen.setdefault("out", o))
    batch = {"batch_size": 1, "rois": torch.tensor([[[5.0, 0, 0, 4, 2, 1.5, 0]]]),
             "roi_labels": torch.ones(1, 1, dtype=torch.long), "roi_scores": torch.ones(1, 1)}
    with torch.no_grad():
        head(batch)
    assert seen["out"][0, 0, 0] == 2.0 and seen["out"][0, 1:].abs().sum() == 0


def test_a_set_abstraction_width_that_contradicts_the_backbone_is_a_config_error():
    cfg = tiny_model_config()
    cfg["PFE"]["SA_LAYER"]["x_conv3"]["INPUT_CHANNELS"] = 64  # the small backbone's x_conv3 has 32
    with pytest.raises(InputError, match="x_conv3.INPUT_CHANNELS is 64 but the 3D backbone's x_conv3 has 32"):
        build_detector(cfg, 2, ["Car", "Pedestrian"], TINY_RANGE, TINY_VOXEL, source="pv_rcnn.yaml")


def test_voxel_set_abstraction_samples_keypoints_from_voxel_centres():
    cfg = vsa_config(num_keypoints=8)
    cfg["POINT_SOURCE"] = "voxel_centers"
    vsa = VoxelSetAbstraction(cfg, VOXEL_SIZE, POINT_CLOUD_RANGE, num_bev_features=5, num_rawpoint_features=4).eval()
    batch = vsa_batch()
    conv1 = batch["multi_scale_3d_features"]["x_conv1"]
    batch["voxel_coords"] = conv1.coords  # batch, z, y, x at the input resolution
    coords = vsa(batch)["point_coords"]
    origin, size = torch.tensor(POINT_CLOUD_RANGE[:3]), torch.tensor(VOXEL_SIZE)
    for b in range(2):
        zyx = conv1.coords[conv1.coords[:, 0] == b, 1:4].float()
        centres = (zyx[:, [2, 1, 0]] + 0.5) * size + origin
        kp = coords[coords[:, 0] == b, 1:4]
        assert kp.shape == (8, 3) and torch.allclose(kp[0], centres[0])
        assert bool(((kp[:, None] - centres[None]).abs().amax(dim=2).min(dim=1).values < 1e-5).all())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_pv_rcnn_runs_on_cuda_as_on_cpu():
    torch.manual_seed(0)
    model = build_detector(tiny_model_config(), 2, ["Car", "Pedestrian"], TINY_RANGE, TINY_VOXEL).eval()
    cuda = torch.device("cuda")

    def keypoint_stage(net, batch):
        with torch.no_grad():
            for module in net.module_list:
                batch = module(batch)
                if module is net.point_head:
                    return batch

    cpu_out = keypoint_stage(model, tiny_batch())
    model.to(cuda)
    gpu_out = keypoint_stage(model, {k: v.to(cuda) if torch.is_tensor(v) else v for k, v in tiny_batch().items()})
    assert torch.equal(gpu_out["point_coords"].cpu(), cpu_out["point_coords"])
    torch.testing.assert_close(gpu_out["point_features"].cpu(), cpu_out["point_features"], atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(gpu_out["point_cls_scores"].cpu(), cpu_out["point_cls_scores"], atol=1e-4, rtol=1e-4)
    model.train()
    loss = model({k: v.to(cuda) if torch.is_tensor(v) else v for k, v in tiny_batch().items()})[0]["loss"]
    loss.backward()
    assert loss.device.type == "cuda" and torch.isfinite(loss)
    with torch.no_grad():
        preds, _ = model.eval()({k: v.to(cuda) if torch.is_tensor(v) else v for k, v in tiny_batch().items()})
    assert all(p["pred_boxes"].device.type == "cuda" for p in preds)
