"""LiDAR 3D object detection: box and point operators, detectors (OpenPCDet layout)."""
