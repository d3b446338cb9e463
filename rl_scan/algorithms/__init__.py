"""Learning algorithms: POCA, the PPO baseline and MetaPOCA (meta-MRSS); ``registry`` names them."""
