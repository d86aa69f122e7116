"""Keep the process environment array that OpenDSS's library captured valid for the life of the process.

DSS C-API (``libdss_capi``) is written in FreePascal. A FreePascal shared library copies the C ``environ`` pointer
when it is loaded and reads the environment through that copy ever after (``fpgetenv``: e.g. ``LANG`` for the
code page whenever a text file is assigned, which ``ctx_New`` does). glibc's ``setenv``/``putenv`` reallocate
the array they allocated themselves when a variable is added, so after the first new variable (``os.environ[...]
= ...``; pytest sets ``PYTEST_CURRENT_TEST`` around every test) that copy may point into freed memory. Reading
it segfaulted in ``ctx_New`` (``FPGETENV`` <- ``GETSTANDARDCODEPAGE`` <- ``ASSIGN``, seen under gdb), at random,
most often in a thread's first call.

``pin()``, called before the library is loaded, points ``environ`` at a copy the process owns and never frees:
the library captures that copy; glibc, on the next new variable, copies it into an array of its own instead of
reallocating it (it only reallocates the array it allocated), so the pinned copy stays valid (its contents are
the environment at load time, which is all the library reads). Linux only; a no-op elsewhere.
"""

from __future__ import annotations

import ctypes
import sys

__all__ = ["pin"]

_pinned: list[object] = []  # the array and its strings, kept alive for the life of the process


def pin() -> None:
    """Point the C ``environ`` at a process-owned copy of itself (once; Linux with glibc)."""
    if _pinned or not sys.platform.startswith("linux"):
        return
    try:
        environ = ctypes.c_void_p.in_dll(ctypes.CDLL(None), "environ")
    except (OSError, ValueError):
        return
    if not environ.value:  # no environment block at all: nothing to pin
        return
    entries = ctypes.cast(environ.value, ctypes.POINTER(ctypes.c_char_p))
    strings = []
    i = 0
    while entries[i] is not None:
        strings.append(ctypes.create_string_buffer(entries[i]))
        i += 1
    array = (ctypes.c_char_p * (len(strings) + 1))(*[ctypes.cast(s, ctypes.c_char_p) for s in strings], None)
    _pinned.extend([array, strings])
    environ.value = ctypes.addressof(array)
