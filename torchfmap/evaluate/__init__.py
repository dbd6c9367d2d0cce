"""Evaluating maps against ground truth: geodesic errors, PCK, shape distances and pair discovery
(:mod:`.scores`), ground-truth correspondences (:mod:`.ground_truth`), partial collections and
overlap IoU (:mod:`.partial`), collections of pairs (:mod:`.collection`) and their saved scores
(:mod:`.saved_pairs`)."""
