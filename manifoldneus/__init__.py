"""Shared maths and I/O of the manifoldneus pipeline (stages live in ``stages/``)."""
