"""OpenPCDet's PV-RCNN state dict (tools/cfgs/kitti_models/pv_rcnn.yaml): key -> shape.

Written by hand from OpenPCDet's module definitions: 3 classes (Car, Pedestrian,
Cyclist), 4 point features (x, y, z, intensity), spconv 2.x weight layout
(out, kD, kH, kW, in). BatchNorm entries expand to weight, bias, running_mean,
running_var and num_batches_tracked.
"""

from __future__ import annotations


def _bn(prefix: str, c: int) -> dict[str, tuple[int, ...]]:
    return {
        f"{prefix}.weight": (c,), f"{prefix}.bias": (c,), f"{prefix}.running_mean": (c,),
        f"{prefix}.running_var": (c,), f"{prefix}.num_batches_tracked": (),
    }


def _conv_bn(conv: str, bn: str, weight: tuple[int, ...], bn_channels: int | None = None) -> dict[str, tuple[int, ...]]:
    """A bias-free conv and its BatchNorm (channels = weight[0] unless given)."""
    return {f"{conv}.weight": weight, **_bn(bn, weight[0] if bn_channels is None else bn_channels)}


def _sa_module(prefix: str, c_in: int, mlps: list[list[int]]) -> dict[str, tuple[int, ...]]:
    """StackSAModuleMSG: per scale Conv2d(1x1, no bias) - BN2d - ReLU per MLP step."""
    keys: dict[str, tuple[int, ...]] = {}
    for s, spec in enumerate(mlps):
        chans = [c_in + 3, *spec]
        for k, (a, b) in enumerate(zip(chans[:-1], chans[1:])):
            keys.update(_conv_bn(f"{prefix}.mlps.{s}.{3 * k}", f"{prefix}.mlps.{s}.{3 * k + 1}", (b, a, 1, 1)))
    return keys


def pv_rcnn_kitti_keys() -> dict[str, tuple[int, ...]]:
    keys: dict[str, tuple[int, ...]] = {"global_step": (1,)}
    # backbone_3d: VoxelBackBone8x on 4 input channels
    keys.update(_conv_bn("backbone_3d.conv_input.0", "backbone_3d.conv_input.1", (16, 3, 3, 3, 4)))
    keys.update(_conv_bn("backbone_3d.conv1.0.0", "backbone_3d.conv1.0.1", (16, 3, 3, 3, 16)))
    for stage, (c_in, c_out) in {2: (16, 32), 3: (32, 64), 4: (64, 64)}.items():
        keys.update(_conv_bn(f"backbone_3d.conv{stage}.0.0", f"backbone_3d.conv{stage}.0.1", (c_out, 3, 3, 3, c_in)))
        for j in (1, 2):
            keys.update(_conv_bn(f"backbone_3d.conv{stage}.{j}.0", f"backbone_3d.conv{stage}.{j}.1",
                                 (c_out, 3, 3, 3, c_out)))
    keys.update(_conv_bn("backbone_3d.conv_out.0", "backbone_3d.conv_out.1", (128, 3, 1, 1, 64)))
    # backbone_2d: BaseBEVBackbone, LAYER_NUMS [5, 5], NUM_FILTERS [128, 256], 256 BEV channels in
    for i, (c_in, c) in enumerate([(256, 128), (128, 256)]):
        keys.update(_conv_bn(f"backbone_2d.blocks.{i}.1", f"backbone_2d.blocks.{i}.2", (c, c_in, 3, 3)))
        for j in range(5):
            keys.update(_conv_bn(f"backbone_2d.blocks.{i}.{4 + 3 * j}", f"backbone_2d.blocks.{i}.{5 + 3 * j}",
                                 (c, c, 3, 3)))
    # ConvTranspose2d weights are (in, out, kH, kW)
    keys.update(_conv_bn("backbone_2d.deblocks.0.0", "backbone_2d.deblocks.0.1", (128, 256, 1, 1), 256))
    keys.update(_conv_bn("backbone_2d.deblocks.1.0", "backbone_2d.deblocks.1.1", (256, 256, 2, 2)))
    # dense_head: AnchorHeadSingle, 3 classes x 2 rotations = 6 anchors per location, 512 channels in
    for name, c in {"conv_cls": 6 * 3, "conv_box": 6 * 7, "conv_dir_cls": 6 * 2}.items():
        keys[f"dense_head.{name}.weight"] = (c, 512, 1, 1)
        keys[f"dense_head.{name}.bias"] = (c,)
    # pfe: VoxelSetAbstraction; x_conv1..4 inputs 16, 32, 64, 64; raw points 1 extra channel
    for i, (c_in, c) in enumerate([(16, 16), (32, 32), (64, 64), (64, 64)]):
        keys.update(_sa_module(f"pfe.SA_layers.{i}", c_in, [[c, c], [c, c]]))
    keys.update(_sa_module("pfe.SA_rawpoints", 1, [[16, 16], [16, 16]]))
    fused_in = 256 + 32 + 64 + 128 + 128 + 32  # bev + x_conv1..4 + raw_points
    keys["pfe.vsa_point_feature_fusion.0.weight"] = (128, fused_in)
    keys.update(_bn("pfe.vsa_point_feature_fusion.1", 128))
    # point_head: PointHeadSimple on the features before fusion, class-agnostic
    keys["point_head.cls_layers.0.weight"] = (256, fused_in)
    keys.update(_bn("point_head.cls_layers.1", 256))
    keys["point_head.cls_layers.3.weight"] = (256, 256)
    keys.update(_bn("point_head.cls_layers.4", 256))
    keys["point_head.cls_layers.6.weight"] = (1, 256)
    keys["point_head.cls_layers.6.bias"] = (1,)
    # roi_head: PVRCNNHead on 128 keypoint channels, 6^3 grid, class-agnostic
    keys.update(_sa_module("roi_head.roi_grid_pool_layer", 128, [[64, 64], [64, 64]]))
    keys.update(_conv_bn("roi_head.shared_fc_layer.0", "roi_head.shared_fc_layer.1", (256, 216 * 128, 1)))
    keys.update(_conv_bn("roi_head.shared_fc_layer.4", "roi_head.shared_fc_layer.5", (256, 256, 1)))
    for name, c_out in {"cls_layers": 1, "reg_layers": 7}.items():
        keys.update(_conv_bn(f"roi_head.{name}.0", f"roi_head.{name}.1", (256, 256, 1)))
        keys.update(_conv_bn(f"roi_head.{name}.4", f"roi_head.{name}.5", (256, 256, 1)))
        keys[f"roi_head.{name}.7.weight"] = (c_out, 256, 1)
        keys[f"roi_head.{name}.7.bias"] = (c_out,)
    return keys
