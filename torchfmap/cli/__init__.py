"""The command line ``torchfmap``: the parser and ``main`` (:mod:`.parser`), the classical and
learned commands (:mod:`.commands`, :mod:`.train`), argparse types (:mod:`.types`) and messages in
flag terms (:mod:`.messages`). Entry point ``torchfmap.cli:main``."""

from .parser import build_parser, check_outputs, in_cli_terms, main

__all__ = ["build_parser", "check_outputs", "in_cli_terms", "main"]
