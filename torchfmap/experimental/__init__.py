"""Experiments kept available and tested, but not part of the core API: methods measured not
to pay against the core's own (their benchmarks in ``bench/`` say by how much), kept as
options and measured negatives. Nothing here is imported by the core; import each submodule
by name (e.g. ``torchfmap.experimental.seeded``): this package imports none of them.
"""
