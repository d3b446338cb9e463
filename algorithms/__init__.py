"""Learning algorithms (POCA, PPO baseline, meta-MRSS) land here: issues #4 and #5."""
