"""What a run hands out: the mesh (``meshing``),
evaluation (``evaluation``) and its metrics (``metrics``), other tools' formats (``export``) and
the self-contained HTML viewer (``viewer`` with ``viewer_assets/``). It may import
``geometry``, ``neural``, ``data`` and ``config``."""
