"""Captures: the on-disk format every later stage reads (:mod:`~gra_mi.capture.dataset`), and the synthetic,
path-traced lightstage capture that stands in for real data (:mod:`~gra_mi.capture.synthetic`)."""
