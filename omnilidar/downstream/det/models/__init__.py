"""Detectors in OpenPCDet's layout (module and parameter names), native PyTorch.

One module per OpenPCDet module; ``build_detector`` (in :mod:`.detector`) builds
one from the MODEL section of an OpenPCDet config.
"""

from omnilidar.downstream.det.models.detector import build_detector

__all__ = ["build_detector"]
