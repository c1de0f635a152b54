"""The neural surface and its training: the fields (``field``; ``grid_encoding`` with its C++
kernel in ``csrc/``), NeuS rendering (``render``), the losses (``losses``), the trainer
(``train``), the MaVOS-gated coarse-to-fine encoding
(``gate``), per-view pose corrections (``pose_correction``) and poses refined against a frozen
field (``pose_alignment``). It may import ``geometry``, ``data`` and ``config``."""
