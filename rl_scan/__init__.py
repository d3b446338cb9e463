"""rl-scan: learning multi-robot 3D scanning with Ray RLlib (see DESIGN.md in the docs)."""

__version__ = "0.1.0"
