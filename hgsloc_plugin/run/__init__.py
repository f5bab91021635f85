"""Running many queries: lockstep batches (``lockstep``), Ray workers (``distributed``), the one batch loop
(``batch``), the public refiner (``plugin.HGSLocPlugin``) and pose files end to end (``pipeline``)."""
