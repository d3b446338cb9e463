"""The 3D scanning simulator core. Imports no RL library."""
