"""Operators of the detectors, pure PyTorch (any device): ``nms`` and ``sampling``.

Box geometry (rotated IoU, points in boxes) lives in ``omnilidar.geometry``.
"""
