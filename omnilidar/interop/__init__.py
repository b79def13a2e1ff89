"""Checkpoint layouts of other toolkits, converted to this package's networks: ``lidm``
(LiDM / SPVNAS torchsparse MinkowskiNet and SPVCNN) and ``mmdet3d`` (mmdetection3d's MinkUNet and
SPVCNN segmentors; torchsparse, spconv 1.x and 2.x kernels). Used by the metrics' extractors and
the downstream labelers alike; builds networks through ``omnilidar.segnets``.
"""
