"""MaVOS view scheduling: co-visibility, spectral embedding and the schedules (``mavos``,
numpy and scipy only). It imports nothing of the package but ``config``."""
