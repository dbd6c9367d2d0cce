"""Data: small synthetic meshes for tests and the shipped demo pair."""

from .synthetic import demo_pair, demo_pair_paths, icosphere, make_demo_pair, stretch_deform

__all__ = ["demo_pair", "demo_pair_paths", "icosphere", "make_demo_pair", "stretch_deform"]
