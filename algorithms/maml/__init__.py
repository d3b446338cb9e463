"""meta-MRSS: MAML over POCA (``MetaPOCA``) on RLlib's TorchMetaLearner API."""

from rl_scan.algorithms.maml.meta_poca import MetaPOCA, MetaPOCAConfig, meta_poca_config

__all__ = ["MetaPOCA", "MetaPOCAConfig", "meta_poca_config"]
