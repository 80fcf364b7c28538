"""The brains: every Self Reward Design (SRD) model of the project, one module each."""
