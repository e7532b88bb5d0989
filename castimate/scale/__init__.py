"""Scale-out on Dask distributed: batches of recordings (:mod:`.batch`), Monte Carlo studies
(:mod:`.montecarlo`) and experiment plans (:mod:`.plan`) on one engine (:mod:`.engine`); the
arithmetic apart in :mod:`.stats`. Pages and figures are in :mod:`castimate.report.scale`."""
