"""The as-built lens model: what printing and polishing do to a designed lens.

``tolerances`` holds the statistical model (one ``ToleranceComponent`` per physical
effect, its TOML file and the sampler ``sample_as_built``); ``lens_params`` turns it into
the finite parameter vector theta of one as-built lens that the joint calibration
estimates. It sits below ``design`` (robust design samples it) and ``calibration`` (the
joint fit's nuisance parameters) and uses only ``optics``.
"""
