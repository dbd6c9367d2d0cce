"""Matching two shapes: :func:`torchfmap.match` (:mod:`.pipeline`) and its steps: the solve
(:mod:`.solve`), the landmark default (:mod:`.landmark_default`), partial shapes
(:mod:`.partial`), the result and its one refinement guard (:mod:`.results`), the scores of a
map without ground truth it chooses and guards by (:mod:`.quality`), and its input checks
(:mod:`.checks`)."""
