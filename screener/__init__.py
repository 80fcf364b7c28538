"""The inspector: reads a submitted manifest weight by weight and probes its behaviour."""
