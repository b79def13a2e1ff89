"""Sensors, scans and boxes: the bottom layer that io/, data/ and every stage share.

Imports nothing from the rest of the package except ``omnilidar.errors``."""
