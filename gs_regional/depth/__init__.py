from gs_regional.depth import depth_anything  # noqa: F401
