"""Measuring refinements: errors against ground truth (``evaluate``), noisy priors (``noise``), figures (``viz``)."""
