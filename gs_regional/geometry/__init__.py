from gs_regional.geometry import gaussian_model  # noqa: F401
