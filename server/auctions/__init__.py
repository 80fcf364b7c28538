"""Auctions: the steps that move them, their service, remote round uploads."""
