"""Scanning environments: the simulator core (``sim``) and its RLlib/PettingZoo adapters."""
