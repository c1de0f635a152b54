"""Structure from motion: SfM through pycolmap (``mapper``, which its importers name ``sfm``), the
method's initialisation logic around COLMAP (``pose_init``) and the rounds' correspondence term
with per-view acceptance of pose updates (``correspondence``). It may import ``geometry``,
``data``, ``scheduling`` (the co-visibility matrix) and ``config``."""
