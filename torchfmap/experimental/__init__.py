"""Experiments kept available and tested, outside the core API: nothing in :mod:`torchfmap`
imports them. Import the module you want, e.g. :mod:`torchfmap.experimental.stages`."""
