"""Experiments: Tune runs (``launch``), ablation studies (``ablate``), the meta-MRSS protocol."""
