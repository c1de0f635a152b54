"""Geometry and cameras: every camera and pose convention and its maths (``cameras``), camera
rays and sphere bounds (``rays``), pose errors against ground truth (``pose_metrics``), where
the object is from SfM points without masks (``object_region``). With
``data`` the bottom floor of the library: it may import ``config`` and ``data`` only, and every
other sub-package may import it."""
