"""Synthetic stand-ins with known ground truth: the demo's tables (:mod:`.tables`), py-feat's own CSV layouts
(:mod:`.pyfeat`) and the true release of the generating model (:mod:`.truth`)."""
