"""SemanticKITTI raw label ids used by the synthetic world, and surface materials.

Ids are the RAW SemanticKITTI ids (label & 0xFFFF); the official learning map
lives in :mod:`omnilidar.io.semantickitti`. Reflectivities are diffuse albedos at
905 nm (0..1) chosen so that synthetic remission statistics per class match real
KITTI scans (asphalt dark, lane paint and vegetation bright, tyres and glass near
zero); each object draws its own value from the class range.
"""

from __future__ import annotations

CAR, BICYCLE, MOTORCYCLE, TRUCK, OTHER_VEHICLE = 10, 11, 15, 18, 20
PERSON, BICYCLIST, MOTORCYCLIST = 30, 31, 32
ROAD, PARKING, SIDEWALK, OTHER_GROUND = 40, 44, 48, 49
BUILDING, FENCE, VEGETATION, TRUNK, TERRAIN, POLE, TRAFFIC_SIGN = 50, 51, 70, 71, 72, 80, 81

GROUND_CLASSES = (ROAD, PARKING, SIDEWALK, OTHER_GROUND, TERRAIN)
THING_CLASSES = (CAR, BICYCLE, MOTORCYCLE, TRUCK, OTHER_VEHICLE, PERSON, BICYCLIST, MOTORCYCLIST)

# (low, high) diffuse reflectivity per class; objects draw uniformly in the range.
REFLECTIVITY: dict[int, tuple[float, float]] = {
    ROAD: (0.34, 0.48),
    PARKING: (0.34, 0.50),
    SIDEWALK: (0.40, 0.56),
    OTHER_GROUND: (0.36, 0.52),
    TERRAIN: (0.42, 0.62),
    BUILDING: (0.28, 0.62),
    FENCE: (0.28, 0.55),
    VEGETATION: (0.42, 0.66),
    TRUNK: (0.32, 0.50),
    POLE: (0.32, 0.55),
    TRAFFIC_SIGN: (0.80, 0.98),  # retro-reflective sheeting
    CAR: (0.06, 0.55),  # dark to light paint
    TRUCK: (0.15, 0.50),
    OTHER_VEHICLE: (0.15, 0.50),
    PERSON: (0.15, 0.45),
    BICYCLIST: (0.15, 0.45),
    BICYCLE: (0.15, 0.40),
    MOTORCYCLE: (0.10, 0.40),
    MOTORCYCLIST: (0.15, 0.45),
}
LANE_MARKING_REFLECTIVITY = (0.55, 0.75)
TYRE_REFLECTIVITY = (0.01, 0.04)  # near-black rubber: mostly zero remission
GLASS_REFLECTIVITY = (0.01, 0.05)

# Box names of the classes that carry 3D boxes (KITTI / Pi3DET naming).
BOX_NAMES = {CAR: "Car", PERSON: "Pedestrian"}
