"""Shared maths and I/O of the manifoldneus pipeline (stages live in ``stages/``)."""

__version__ = "0.4.0"  # bumped with every entry of docs/CHANGELOG.md that changes results or files
