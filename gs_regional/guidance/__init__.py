from gs_regional.guidance import instructpix2pix  # noqa: F401
