"""Experiments kept available and tested, outside the core API (nothing in the core imports them). This
package imports none of its submodules: import each by name, e.g. :mod:`torchfmap.experimental.seeded`
or :mod:`torchfmap.experimental.stages` (torch)."""
