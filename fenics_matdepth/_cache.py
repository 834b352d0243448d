"""numba's on-disk cache, invalidated by any change to the package's sources.

numba keys a cached kernel on the source file that defines it (modification time and size)
only. Our kernels compile functions of other modules into their machine code
(``contact/kernels.py`` calls the clipper of ``geometry/clip.py``, and reads its constants at
compile time; ``bvh.py`` inlines ``distance.py``'s helpers), so after an edit of
``clip.py`` numba would load the old machine code of every kernel that uses it, silently. To
prevent that, :func:`install` wraps numba's cache locators so that, for functions defined in
this package, the stamp also holds a hash of all the package's ``.py`` sources: any edit of any
module recompiles every kernel of the package on its next use (the first-use notice of
`fenics_matdepth._jit` then says so), and nothing stale is ever loaded. Functions of other
packages keep numba's own stamp.

The locator classes are numba internals (``numba.core.caching.CacheImpl._locator_classes``,
``_CacheImpl`` before numba 0.63); if a numba release moves them, :func:`install` leaves the
cache as numba has it and returns False.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

__all__ = ["install", "package_stamp"]

_PACKAGE_DIR = Path(__file__).resolve().parent


def package_stamp(package_dir: Path = _PACKAGE_DIR) -> str:
    """SHA-1 of the relative paths and contents of every ``.py`` file of the package."""
    digest = hashlib.sha1()
    for path in sorted(package_dir.rglob("*.py")):
        digest.update(path.relative_to(package_dir).as_posix().encode())
        digest.update(b"\0")
        digest.update(path.read_bytes())
    return digest.hexdigest()


def _in_package(py_file: str | None) -> bool:
    if not py_file:
        return False
    try:
        return Path(py_file).resolve().is_relative_to(_PACKAGE_DIR)
    except OSError:
        return False


def install() -> bool:
    """Make numba's cache stamps of this package's functions include :func:`package_stamp`.

    Idempotent; must run before the package's ``@njit(cache=True)`` functions are defined (the
    package's ``__init__`` calls it first).

    Returns:
        Whether the locators could be wrapped.
    """
    from numba.core import caching

    impl = getattr(caching, "CacheImpl", None) or getattr(caching, "_CacheImpl", None)
    classes = getattr(impl, "_locator_classes", None)
    if not isinstance(classes, list):
        return False
    if any(getattr(cls, "_matdepth_stamp", None) for cls in classes):
        return True
    stamp = package_stamp()

    def wrap(base):
        def get_source_stamp(self):
            inner = base.get_source_stamp(self)
            if _in_package(getattr(self, "_py_file", None)):
                return (inner, stamp)
            return inner

        return type(
            base.__name__,
            (base,),
            {"get_source_stamp": get_source_stamp, "_matdepth_stamp": stamp},
        )

    impl._locator_classes = [wrap(cls) for cls in classes]
    return True


INSTALLED = install()
