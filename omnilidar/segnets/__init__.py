"""The sparse segmentation networks (MinkUNet, SPVCNN) and the voxelisation that feeds them,
on ``omnilidar.sparse``: used by the downstream students and labelers and by the FSVD/FPVD
feature extractors alike, importing nothing of either.
"""
