"""Test support: factories, reference loops, corpora and harnesses shared by the tests and the
benchmarks, so that no test module imports another."""
