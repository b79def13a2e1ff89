"""OmniLiDAR generative data augmentation pipeline."""

__version__ = "0.1.0"
