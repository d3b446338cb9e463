"""Tune launches and Optuna ablation studies land here: issue #6."""
