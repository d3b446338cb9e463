"""MA-POCA for RLlib: centralized counterfactual critic, decentralized actors per robot kind."""

from rl_scan.algorithms.poca.poca import POCA, POCAConfig, poca_config, team_layout

__all__ = ["POCA", "POCAConfig", "poca_config", "team_layout"]
