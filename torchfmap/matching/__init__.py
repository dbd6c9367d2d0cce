"""Matching two shapes: :func:`torchfmap.match` (:mod:`.pipeline`) and its steps (:mod:`.solve`,
:mod:`.landmark_default`, :mod:`.partial`, :mod:`.results`, :mod:`.quality`, :mod:`.checks`)."""
