"""LiDAR semantic segmentation: voxelisation, MinkUNet and SPVCNN."""
