from gs_regional.guidance import instructpix2pix, simulated_editor  # noqa: F401
