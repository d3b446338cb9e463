"""Reports from rl-scan results: statistics, figures, Markdown/HTML (``build.py``)."""
