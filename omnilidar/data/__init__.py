"""Sensors, scans, range images and the synthetic LiDAR world."""
