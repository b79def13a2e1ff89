"""A detector as OpenPCDet's Detector3DTemplate: the MODEL config's modules, built
and run in OpenPCDet's order, with its attribute names (so state dict keys match).

``build_detector(model_cfg, num_class, class_names, point_cloud_range, voxel_size)``
takes the MODEL section of an OpenPCDet config (upper-case keys) as a plain dict.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from omnilidar.errors import InputError

from omnilidar.downstream.det.models.backbone_2d import BaseBEVBackbone
from omnilidar.downstream.det.models.backbone_3d import VoxelBackBone8x
from omnilidar.downstream.det.models.dense_heads import AnchorHeadSingle
from omnilidar.downstream.det.models.map_to_bev import HeightCompression
from omnilidar.downstream.det.models.point_head_simple import PointHeadSimple
from omnilidar.downstream.det.models.post_processing import post_processing
from omnilidar.downstream.det.models.pvrcnn_head import PVRCNNHead
from omnilidar.downstream.det.models.spconv_layout import adapt_spconv_weights
from omnilidar.downstream.det.models.vfe import MeanVFE
from omnilidar.downstream.det.models.voxel_rcnn_head import VoxelRCNNHead
from omnilidar.downstream.det.models.voxel_set_abstraction import VoxelSetAbstraction

# OpenPCDet's module order: (config key, attribute name).
MODULE_TOPOLOGY = (("VFE", "vfe"), ("BACKBONE_3D", "backbone_3d"), ("MAP_TO_BEV", "map_to_bev_module"),
                   ("PFE", "pfe"), ("BACKBONE_2D", "backbone_2d"), ("DENSE_HEAD", "dense_head"),
                   ("POINT_HEAD", "point_head"), ("ROI_HEAD", "roi_head"))

# Module classes by config key and NAME; other detectors' modules register here.
MODULES: dict[str, dict[str, type]] = {
    "VFE": {"MeanVFE": MeanVFE},
    "BACKBONE_3D": {"VoxelBackBone8x": VoxelBackBone8x},
    "MAP_TO_BEV": {"HeightCompression": HeightCompression},
    "PFE": {"VoxelSetAbstraction": VoxelSetAbstraction},
    "BACKBONE_2D": {"BaseBEVBackbone": BaseBEVBackbone},
    "DENSE_HEAD": {"AnchorHeadSingle": AnchorHeadSingle},
    "POINT_HEAD": {"PointHeadSimple": PointHeadSimple},
    "ROI_HEAD": {"VoxelRCNNHead": VoxelRCNNHead, "PVRCNNHead": PVRCNNHead},
}
DETECTORS = ("VoxelRCNN", "PVRCNN")


def _cls(key: str, name: str) -> type:
    if name not in MODULES[key]:
        known = ", ".join(sorted(MODULES[key])) or "none"
        raise ValueError(f"MODEL.{key}.NAME {name!r} is not a known module (known: {known})")
    return MODULES[key][name]


class Detector3D(nn.Module):
    """The chain of modules; forward as OpenPCDet's two-stage detectors."""

    def __init__(self, model_cfg: dict, num_class: int, class_names: list[str], point_cloud_range, voxel_size,
                 num_point_features: int = 4, sparse_backend: str = "torch", seed: int = 0):
        super().__init__()
        self.model_cfg = model_cfg
        self.num_class = num_class
        self.class_names = list(class_names)
        self.register_buffer("global_step", torch.zeros(1, dtype=torch.long))
        pcr = [float(v) for v in point_cloud_range]
        vs = [float(v) for v in voxel_size]
        grid = [int(round((pcr[i + 3] - pcr[i]) / vs[i])) for i in range(3)]
        # Sampling inside the heads (anchor subsampling, RoI sampling) draws from here.
        self.sampling_generator = torch.Generator().manual_seed(int(seed))
        info = {"num_rawpoint_features": num_point_features, "num_point_features": num_point_features,
                "grid_size": grid, "point_cloud_range": pcr, "voxel_size": vs,
                "depth_downsample_factor": None}
        self.module_list: list[nn.Module] = []
        for key, attr in MODULE_TOPOLOGY:
            cfg = model_cfg.get(key)
            module = None if cfg is None else self._build(key, cfg, info, sparse_backend)
            setattr(self, attr, module)
            if module is not None:
                self.module_list.append(module)

    def _build(self, key: str, cfg: dict, info: dict, sparse_backend: str) -> nn.Module:
        cls = _cls(key, cfg["NAME"])
        common = dict(model_cfg=cfg, grid_size=info["grid_size"], point_cloud_range=info["point_cloud_range"],
                      voxel_size=info["voxel_size"], generator=self.sampling_generator)
        agnostic_classes = 1 if cfg.get("CLASS_AGNOSTIC", False) else self.num_class
        two_stage = self.model_cfg.get("ROI_HEAD") is not None
        if key == "VFE":
            m = cls(num_point_features=info["num_rawpoint_features"], **common)
            info["num_point_features"] = m.get_output_feature_dim()
        elif key == "BACKBONE_3D":
            m = cls(input_channels=info["num_point_features"], sparse_backend=sparse_backend, **common)
            info["num_point_features"] = m.num_point_features
            info["backbone_channels"] = getattr(m, "backbone_channels", None)
            info["backbone_bev_features"] = getattr(m, "num_bev_features", None)
            out_shape = getattr(m, "out_spatial_shape", None)
            info["bev_size"] = None if out_shape is None else tuple(out_shape[1:])
        elif key == "MAP_TO_BEV":
            m = cls(**common)
            expected = info.get("backbone_bev_features")
            if expected is not None and m.num_bev_features != expected:
                raise ValueError(f"MAP_TO_BEV.NUM_BEV_FEATURES is {m.num_bev_features} but the 3D backbone on "
                                 f"this grid gives {expected} (its output width x z slices)")
            info["num_bev_features"] = m.num_bev_features
        elif key == "PFE":
            m = cls(num_bev_features=info.get("num_bev_features"), num_rawpoint_features=info["num_rawpoint_features"],
                    backbone_channels=info.get("backbone_channels"), **common)
            info["num_point_features"] = m.num_point_features
            info["num_point_features_before_fusion"] = m.num_point_features_before_fusion
        elif key == "BACKBONE_2D":
            m = cls(input_channels=info["num_bev_features"], **common)
            info["num_bev_features"] = m.num_bev_features
            if info.get("bev_size") is not None and hasattr(m, "output_size"):
                info["bev_size"] = m.output_size(*info["bev_size"])
        elif key == "DENSE_HEAD":
            m = cls(input_channels=info["num_bev_features"], num_class=self.num_class, class_names=self.class_names,
                    predict_boxes_when_training=two_stage, **common)
            for anchors in getattr(m, "anchors", []):
                if info.get("bev_size") is not None and tuple(anchors.shape[1:3]) != info["bev_size"]:
                    raise ValueError(f"DENSE_HEAD anchors lie on a {tuple(anchors.shape[1:3])} map (grid / "
                                     f"feature_map_stride) but the BEV features are {info['bev_size']} (y, x)")
        elif key == "POINT_HEAD":
            channels = info["num_point_features_before_fusion"] if cfg.get("USE_POINT_FEATURES_BEFORE_FUSION", False) \
                else info["num_point_features"]
            m = cls(input_channels=channels, num_class=agnostic_classes, predict_boxes_when_training=two_stage,
                    **common)
        else:  # ROI_HEAD
            m = cls(input_channels=info["num_point_features"], backbone_channels=info.get("backbone_channels"),
                    num_class=agnostic_classes, **common)
        return m

    def load_openpcdet_state(self, model_state: dict[str, torch.Tensor], strict: bool = True):
        """Load an OpenPCDet checkpoint's ``model_state`` (spconv 1.x sparse weights permuted)."""
        return self.load_state_dict(adapt_spconv_weights(model_state, self.state_dict()), strict=strict)

    def forward(self, batch_dict: dict):
        for module in self.module_list:
            batch_dict = module(batch_dict)
        if self.training:
            loss, tb_dict, disp_dict = self.get_training_loss()
            return {"loss": loss}, tb_dict, disp_dict
        return post_processing(batch_dict, self.model_cfg["POST_PROCESSING"], self.num_class)

    def get_training_loss(self):
        loss, tb_dict = self.dense_head.get_loss()
        if self.point_head is not None:
            point_loss, tb_dict = self.point_head.get_loss(tb_dict)
            loss = loss + point_loss
        if self.roi_head is not None:
            rcnn_loss, tb_dict = self.roi_head.get_loss(tb_dict)
            loss = loss + rcnn_loss
        return loss, tb_dict, {}


def build_detector(model_cfg: dict, num_class: int, class_names: list[str], point_cloud_range, voxel_size,
                   source: str | None = None, **kwargs) -> Detector3D:
    """The detector of an OpenPCDet MODEL config (``NAME`` one of DETECTORS).

    kwargs: ``num_point_features`` (raw point features, default 4: x, y, z,
    intensity), ``sparse_backend`` ("torch", "spconv", "auto"), ``seed`` of the
    heads' sampling generator. A bad config raises InputError naming ``source``
    (the config file the MODEL section came from).
    """
    try:
        return _build(model_cfg, num_class, class_names, point_cloud_range, voxel_size, **kwargs)
    except KeyError as err:
        raise InputError(source, f"MODEL config lacks key {err.args[0]!r}") from None
    except ValueError as err:
        raise InputError(source, f"MODEL config: {err}") from None


def _build(model_cfg, num_class, class_names, point_cloud_range, voxel_size, **kwargs) -> Detector3D:
    if model_cfg.get("NAME") not in DETECTORS:
        raise ValueError(f"MODEL.NAME {model_cfg.get('NAME')!r} is not one of {', '.join(DETECTORS)}")
    if len(class_names) != num_class:
        raise ValueError(f"num_class is {num_class} but {len(class_names)} class names were given")
    for i in range(3):
        cells = (point_cloud_range[i + 3] - point_cloud_range[i]) / voxel_size[i]
        if not math.isclose(cells, round(cells), abs_tol=1e-3) or round(cells) < 1:
            raise ValueError(f"point_cloud_range {list(point_cloud_range)} is not a whole number of "
                             f"voxels {list(voxel_size)} on axis {i}")
    return Detector3D(model_cfg, num_class, class_names, point_cloud_range, voxel_size, **kwargs)
