"""Detectors in OpenPCDet's layout (module and parameter names), native PyTorch.

One module per OpenPCDet module; ``detector.build_detector`` builds one from the
MODEL section of an OpenPCDet config. Nothing is imported here (so that a stage's
code hash covers only what it uses): ``from omnilidar.downstream.det.models.detector
import build_detector``.
"""
