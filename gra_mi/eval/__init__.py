"""Evaluation against the path-traced truth: :mod:`~gra_mi.eval.lighting` scores relighting under environments."""
