"""Label spaces of the segmentation runs and the maps between them.

A label space is the set of trainable classes a segmentor predicts. Train ids
are 0 (ignore) and 1..K; model logits have K columns (column ``c`` is train id
``c + 1``).

* ``semantickitti``: the official semantic-kitti-api learning map to 19
  classes (:mod:`omnilidar.io.semantickitti`).
* ``nuscenes``: the 16-class nuScenes-lidarseg challenge map of the 32 general
  classes (barrier, bicycle, bus, car, construction_vehicle, motorcycle,
  pedestrian, traffic_cone, trailer, truck, driveable_surface, other_flat,
  sidewalk, terrain, manmade, vegetation). Noise, animal, personal mobility,
  stroller, wheelchair, debris, pushable/pullable, bicycle rack, ambulance,
  police vehicle, static.other and the ego vehicle are ignored.

Generated scans are pseudo-labelled by a SemanticKITTI labeler, so a nuScenes
run (Beam-32 GDA) maps SemanticKITTI train ids into the nuScenes space with
:data:`SEMANTICKITTI_TO_NUSCENES`. The choice follows what each nuScenes class
contains: lane markings and parking are driveable surface, other-ground is
other_flat, building, fence, pole and traffic sign are static.manmade, trunk is
vegetation, other-vehicle is bus (the nuScenes general class of the synthetic
world's other vehicles), and a bicyclist or motorcyclist is part of its
bicycle / motorcycle (nuScenes labels the rider with the vehicle). Four
nuScenes classes (barrier, construction_vehicle, traffic_cone, trailer) have no
SemanticKITTI source and never occur in pseudo-labels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from omnilidar.errors import InputError
from omnilidar.io import semantickitti

NUSCENES_CLASS_NAMES: tuple[str, ...] = (
    "barrier", "bicycle", "bus", "car", "construction_vehicle", "motorcycle", "pedestrian",
    "traffic_cone", "trailer", "truck", "driveable_surface", "other_flat", "sidewalk", "terrain",
    "manmade", "vegetation",
)

# nuScenes-lidarseg general class (0..31) -> 16-class train id (0 = ignore).
NUSCENES_LEARNING_MAP: dict[int, int] = {
    0: 0, 1: 0, 2: 7, 3: 7, 4: 7, 5: 0, 6: 7, 7: 0, 8: 0, 9: 1, 10: 0, 11: 0, 12: 8, 13: 0,
    14: 2, 15: 3, 16: 3, 17: 4, 18: 5, 19: 0, 20: 0, 21: 6, 22: 9, 23: 10, 24: 11, 25: 12,
    26: 13, 27: 14, 28: 15, 29: 0, 30: 16, 31: 0,
}

# SemanticKITTI train id (0..19) -> nuScenes 16-class train id (see the module docstring).
SEMANTICKITTI_TO_NUSCENES: dict[str, str] = {
    "car": "car", "bicycle": "bicycle", "motorcycle": "motorcycle", "truck": "truck",
    "other-vehicle": "bus", "person": "pedestrian", "bicyclist": "bicycle", "motorcyclist": "motorcycle",
    "road": "driveable_surface", "parking": "driveable_surface", "sidewalk": "sidewalk",
    "other-ground": "other_flat", "building": "manmade", "fence": "manmade", "vegetation": "vegetation",
    "trunk": "vegetation", "terrain": "terrain", "pole": "manmade", "traffic-sign": "manmade",
}


@dataclass(frozen=True)
class LabelSpace:
    """A set of trainable classes: names of train ids 1..K."""

    name: str
    class_names: tuple[str, ...]

    @property
    def num_classes(self) -> int:
        """K, the number of trainable classes (logit columns)."""
        return len(self.class_names)

    @property
    def num_ids(self) -> int:
        """K + 1: train ids including ignore (0)."""
        return len(self.class_names) + 1


LABEL_SPACES: dict[str, LabelSpace] = {
    "semantickitti": LabelSpace("semantickitti", semantickitti.CLASS_NAMES),
    "nuscenes": LabelSpace("nuscenes", NUSCENES_CLASS_NAMES),
}


def get_label_space(name: str) -> LabelSpace:
    if name not in LABEL_SPACES:
        raise InputError(None, f"unknown label space {name!r}; known: {', '.join(LABEL_SPACES)}")
    return LABEL_SPACES[name]


def _lut(mapping: dict[int, int], size: int) -> np.ndarray:
    lut = np.zeros(size, np.uint8)
    for src, dst in mapping.items():
        lut[src] = dst
    lut.setflags(write=False)
    return lut


_NUSC_LUT = _lut(NUSCENES_LEARNING_MAP, 256)
_SK_TO_NUSC_LUT = _lut(
    {0: 0, **{semantickitti.CLASS_NAMES.index(s) + 1: NUSCENES_CLASS_NAMES.index(d) + 1
              for s, d in SEMANTICKITTI_TO_NUSCENES.items()}},
    semantickitti.NUM_CLASSES,
)


def nuscenes_train_ids(general: np.ndarray) -> np.ndarray:
    """nuScenes-lidarseg general classes (0..31) -> 16-class train ids (uint8, 0 = ignore)."""
    general = np.asarray(general)
    if general.size and (general.min() < 0 or general.max() > 31):
        raise InputError(None, "nuScenes-lidarseg classes must lie in 0..31")
    return _NUSC_LUT[general.astype(np.int64)]


def semantickitti_to_nuscenes(train_ids: np.ndarray) -> np.ndarray:
    """SemanticKITTI train ids (0..19) -> nuScenes 16-class train ids (uint8)."""
    train_ids = np.asarray(train_ids)
    if train_ids.size and (train_ids.min() < 0 or train_ids.max() >= semantickitti.NUM_CLASSES):
        raise InputError(None, f"SemanticKITTI train ids must lie in 0..{semantickitti.NUM_CLASSES - 1}")
    return _SK_TO_NUSC_LUT[train_ids.astype(np.int64)]
