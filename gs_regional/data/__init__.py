from gs_regional.data import datamodule  # noqa: F401  (register components)
