"""Loaded by every Python process of a rehearsal of the GPU check here (``bash scripts/gpu_check.sh --cpu --site …``,
this folder on PYTHONPATH): the packages the GPU machine will not have (GRA_MI_HIDE_MODULES=pxr,warp,…) cannot be
imported, as there."""

import os
import sys

_HIDDEN = {name for name in os.environ.get("GRA_MI_HIDE_MODULES", "").split(",") if name}

if _HIDDEN:
    import importlib.abc

    class _Hide(importlib.abc.MetaPathFinder):
        def find_spec(self, fullname, path=None, target=None):
            if fullname.split(".")[0] in _HIDDEN:
                raise ModuleNotFoundError(f"No module named '{fullname}' (hidden: a rehearsal of the GPU machine)", name=fullname)
            return None

    sys.meta_path.insert(0, _Hide())
