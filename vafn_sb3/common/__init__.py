"""Shared pieces of the vafn algorithms: the fast-adaptation protocol, its evaluation and its curves."""
