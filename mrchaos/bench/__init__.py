"""The bench: the paper's Table I for policies and baselines on every family (``mrchaos-bench``)."""
