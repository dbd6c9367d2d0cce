"""The command line ``torchfmap`` (entry point ``torchfmap.cli:main``)."""

from .parser import build_parser, check_outputs, in_cli_terms, main

__all__ = ["build_parser", "check_outputs", "in_cli_terms", "main"]
