"""Data and scenes: scene names, layouts and their readers (``scenes``), the synthetic scene
(``synthetic``), zarr, JSON, PLY and PNG files (``io``), the names and readers of the files
stages share (``artifacts``) and the trainer's plain-array input (``views``). With ``geometry`` the bottom floor of the library: it may import
``config`` and ``geometry`` only, and every other sub-package may import it."""
