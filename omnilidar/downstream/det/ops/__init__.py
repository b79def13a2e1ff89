"""Box and point operators of the detectors, pure PyTorch (any device).

Boxes are (N, 7) [x, y, z_center, dx, dy, dz, heading] in the lidar frame, as
OpenPCDet; each operator lives in its own module (iou, nms, points, sampling).
"""
