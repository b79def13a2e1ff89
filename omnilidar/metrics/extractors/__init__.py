"""Feature extractors of the perceptual generation metrics (one module per network).

``rangenet`` (FRD: DarkNet-53, FRID: DarkNet-21), ``sparse_features`` (FSVD:
MinkowskiNet, FPVD: SPVCNN), ``pointnet`` (FPD), ``views`` (the protocol's
per-pixel views of range images), ``weights`` (official weight files and
self-trained checkpoints, with provenance tags) and ``training`` (self-training
on the real training split). Heavy modules are imported by name, not here.
"""

KINDS = ("frd", "frid", "fsvd", "fpvd", "fpd")
METRIC_NAMES = {"frd": "FRD", "frid": "FRID", "fsvd": "FSVD", "fpvd": "FPVD", "fpd": "FPD"}
