"""Experiments kept available and tested, but not part of the core API: methods measured not
to pay against the core's own (their benchmarks in ``bench/`` say by how much), kept as
options and measured negatives. Nothing in the core imports them, and this package imports
none of its submodules: import each by name, e.g. :mod:`torchfmap.experimental.seeded`
(classical) or :mod:`torchfmap.experimental.stages` (torch).
"""
