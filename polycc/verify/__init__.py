"""Independent certification of a cover or a build (``polycc verify``).

Imports nothing of the pipeline: it reads ``cover.npz`` / ``manifest.json`` itself, with its own
point-in-polytope tests (:mod:`.certify`). Inputs are the occupied voxels and the kept
ellipsoids, which the caller derives from the scene again.

``polycc.verify(...)`` calls :func:`polycc.verify.api.verify` (this module is callable, so the
curated name and the package name are one).
"""

import sys
import types

from polycc.verify.api import verify
from polycc.verify.certify import VerifyReport

_DOC = __doc__

__all__ = ["VerifyReport", "verify"]


class _CallableModule(types.ModuleType):
    def __call__(self, *args, **kwargs):
        return verify(*args, **kwargs)

    @property
    def __doc__(self):  # help(polycc.verify) shows the package and the function's parameters
        return _DOC + "\n" + (verify.__doc__ or "")


sys.modules[__name__].__class__ = _CallableModule
