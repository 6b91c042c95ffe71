from gs_regional.systems import reconstruct, regional_edit, in2n  # noqa: F401
