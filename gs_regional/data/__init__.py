from gs_regional.data import datamodule, synthetic  # noqa: F401  (register components)
