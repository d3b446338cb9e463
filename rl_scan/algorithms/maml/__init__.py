"""meta-MRSS: MAML over POCA (``MetaPOCA``) on RLlib's TorchMetaLearner API.

The algorithm classes load on first use, so that ``settings`` (read by the algorithm
registry, and so by ``rl-scan --help``) imports neither Ray nor torch.
"""

__all__ = ["MetaPOCA", "MetaPOCAConfig", "meta_poca_config"]


def __getattr__(name: str):
    if name in __all__:
        from rl_scan.algorithms.maml import meta_poca

        return getattr(meta_poca, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
