"""Physically based effects. Each effect module defines the same interface (see base.py)."""
