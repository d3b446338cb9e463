"""MA-POCA for RLlib: centralized counterfactual critic, decentralized actors per robot kind."""

from rl_scan.algorithms.poca.poca import (
                                          POCA,
                                          POCAConfig,
                                          layout_from_spaces,
                                          poca_config,
                                          team_layout,
)

__all__ = ["POCA", "POCAConfig", "layout_from_spaces", "poca_config", "team_layout"]
