from gs_regional.depth import depth_anything, simulated  # noqa: F401
