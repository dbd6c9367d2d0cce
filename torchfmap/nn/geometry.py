"""Moved: the gradient operator is an operator, :mod:`torchfmap.operators.gradient` (the names
here still work, with a warning)."""

from .._deprecation import module_aliases

__getattr__ = module_aliases(
    __name__,
    {
        "gradient_operator": "torchfmap.operators.gradient.gradient_operator",
        "tangent_frames": "torchfmap.operators.gradient.tangent_frames",
    },
)
