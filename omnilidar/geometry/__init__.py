"""Box geometry at the bottom of the package (beside ``lidar``): used by io, metrics and the
detectors alike, importing nothing of theirs.

Boxes are (N, 7) [x, y, z_center, dx, dy, dz, heading] in the lidar frame, as OpenPCDet.
``boxes``: corners and point membership in NumPy; ``rotated_iou``: rotated BEV and 3D IoU;
``points_in_boxes``: point membership in PyTorch (any device).
"""
