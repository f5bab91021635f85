"""Measuring refinements: errors against ground truth (``evaluate``), noisy priors (``noise``), figures (``viz``),
the map's floor on views with known poses (``floor``)."""
