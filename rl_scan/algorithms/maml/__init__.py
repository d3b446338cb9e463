"""meta-MRSS: first-order MAML-PPO over POCA (``MetaPOCA``) on POCA's own learner.

The algorithm classes load on first use, so that ``settings`` (read by the algorithm
registry, and so by ``rl-scan --help``) imports neither Ray nor torch.
"""

__all__ = ["MetaPOCA", "MetaPOCAConfig", "meta_poca_config"]


def __getattr__(name: str):
    if name in __all__:
        from rl_scan.algorithms.maml import meta_poca

        return getattr(meta_poca, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
