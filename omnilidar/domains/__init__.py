"""Domains: weather and sensor effects, scene specs and the domain builder."""
