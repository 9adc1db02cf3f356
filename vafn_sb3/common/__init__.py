"""Shared pieces of the vafn algorithms: the fast-adaptation protocol and its evaluation."""
