"""Ablation report generation lands here: issue #6."""
