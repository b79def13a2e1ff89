"""Readers and writers for the datasets' own on-disk formats."""
