"""The experiments above the worlds: the auction studies, which screen their patrons
(``screener``) before they play the market (``sim.market``), and the registry of every
experiment kind the CLI and the job backend run.

Layers, lowest first (``tests/test_layering.py`` holds them): ``agents`` (the negotiator
itself), ``sim`` (the market and the worlds), ``screener``, ``studies``, ``server``.
"""
