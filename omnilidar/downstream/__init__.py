"""Downstream perception models trained on real and generated scans."""
