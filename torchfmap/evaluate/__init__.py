"""Evaluating maps against ground truth: scores and pair discovery (:mod:`.scores`, :mod:`.ground_truth`),
partial collections (:mod:`.partial`), collections of pairs (:mod:`.collection`, :mod:`.saved_pairs`)."""
