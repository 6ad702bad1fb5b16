"""Every plot of lensforge (matplotlib, Agg canvas, PNG): ``figure`` (the figure and its
atomic PNG), ``design`` (a design's plots), ``calibration`` (hand-eye and calibration
residuals) and ``study`` (as-built studies, budget and pose-estimation studies).
Plot code draws only: the geometry it shows comes from the library
(``optics.footprint``, ``optics.sensitivity``, ...)."""
